"""rigctl.analysis: the paper's PCA + LDA analyses (Fig. 3, Table 1, Fig. 4) on encoded spiking features.

Modules: ``data`` (read an encoded file through :mod:`rigctl.storage.encoded`: ``FeatureSet`` with the file's
sensor layout and texture set, ``load_features``), ``classify`` (PCA fitted once per
split, nested-PC LDA, ``TextureClassifier`` for the GUI's real-time view), ``tasks`` (textures, groups,
extrapolation, speed extrapolation, real-time), ``stats`` (Welch + Cohen's d, two-proportion z + Cohen's h),
``report`` (Table 1 text, JSON/CSV, Fig. 3-like PNGs), ``model`` (the raw-trials-to-label scikit-learn pipeline,
the force-leak measurement), ``synthetic`` (feature sets with planted confounds).
No device, serial or simulation imports.
"""

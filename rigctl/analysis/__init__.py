"""rigctl.analysis: the paper's PCA + LDA analyses (Fig. 3, Table 1, Fig. 4) on encoded spiking features.

Modules: ``data`` (read the encoded file: ``FeatureSet``, ``load_features``), ``classify`` (PCA fitted once per
split, nested-PC LDA, ``TextureClassifier`` for the GUI's real-time view), ``tasks`` (textures, groups,
extrapolation, speed extrapolation, real-time), ``stats`` (Welch + Cohen's d, two-proportion z + Cohen's h),
``report`` (Table 1 text, JSON/CSV, Fig. 3-like PNGs), ``synthetic`` (feature sets with planted confounds).
No device, serial or simulation imports.
"""

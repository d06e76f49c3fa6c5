# %% [markdown]
# # The paper's analysis on a simulated dataset
#
# A small dataset straight from the simulated rig's model (`rigctl sim dataset`), encoded into SA/RA spike trains and
# their features (`rigctl encode`), then the individual-textures task (`rigctl analyze --task textures`): PCA + LDA,
# 5-fold CV, for the Original and the Speed Scaled variants.

# %%
from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.protocol import load_protocol
from rigctl.analysis import load_features, run_cv
from rigctl.encoding import encode_session
from rigctl.simulation.dataset import generate_dataset

generate_dataset(load_protocol(find_protocol("quick_check")), "d.h5", trials_per_condition=10, seed=0, workers=0,
                 progress=False)
encode_session("d.h5", "d.enc.h5", progress=False)

# %% accuracy against the number of principal components (mean over the repetitions)
fs = load_features("d.enc.h5")
res = run_cv(fs, ("textures",), n_pcs=5, repeats=2, per_texture=10, variants=("original", "speed_scaled"))
for variant, curve in res.curves["textures"].items():
    mean, sd = curve.at(5)
    print(f"{variant:14} 5 PCs: {100 * mean:.1f} % (sd {100 * sd:.1f}; chance {100 / len(fs.texture_classes):.0f} %)")

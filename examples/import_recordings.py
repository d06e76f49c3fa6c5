# %% [markdown]
# # Import your own recordings
#
# Continuous press-and-slide recordings of another lab's 9-taxel sensor at 100 Hz (generated here with a known
# answer; your own `.csv`, `.npy`, `.mat` or NWB files go the same way), cut into one trial per press cycle, each
# file at its own level (`rigctl import --segment cycles`), and the session read back.

# %%
from rigctl.operations import import_recordings
from rigctl.simulation.press_slide import write_press_slide_set
from rigctl.storage.session import open_session

truth = write_press_slide_set("recs")
report = import_recordings(sorted(str(t.path) for t in truth), "lab.h5", rate_hz=100, layout="3x3x1",
                           label_pattern="{texture}__R{recording}", segment_spec="cycles", nan="interpolate",
                           overwrite=True)
print(report.table)
for line in report.warnings:
    print("warning:", line)

# %% where each trial came from
with open_session("lab.h5") as s:
    for i in s.completed_ids()[:3]:
        a = s.trial_attrs(i)
        print(f"trial {i}: {s.plan['texture'][i]} from {a['source_file']} samples "
              f"{a['source_first_sample']}-{a['source_last_sample']} (cycle {a['cycle_index']})")

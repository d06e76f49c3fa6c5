"""``rigctl export``: a session (and its encoded spike trains) in another format; ``rigctl export nwb``."""

from __future__ import annotations

import click

from rigctl.cli import SuggestingGroup
from rigctl.cli.outputs import UsageProblem, check_output
from rigctl.cli.progress import bars, progress_option, show_bars
from rigctl.cli.ranges import SEED, comma_floats


@click.group("export", cls=SuggestingGroup)
def export():
    """Write a session in a format other tools read: NWB, spike events (Tonic's layout), a per-trial layout."""


@export.command("nwb")
@click.argument("session", type=click.Path(exists=True, dir_okay=False))
@click.option("--encoded", type=click.Path(exists=True, dir_okay=False), default=None,
              help="The session's encoded file (rigctl encode): its spike trains become the NWB Units table.")
@click.option("--variants", default=None,
              help="Comma-separated variants whose spike trains are exported (default: the stored ones in real time, "
                   "not speed-scaled).")
@click.option("--out", "out", type=click.Path(dir_okay=False, writable=True), required=True, help="The NWB file to write (.nwb).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@progress_option
@click.option("--keep-nonfinite", is_flag=True,
              help="Export trials whose force or speed readings hold NaN or inf (default: excluded).")
@click.option("--experimenter", "experimenters", multiple=True, metavar="'LAST, FIRST'",
              help="Who ran the session (repeat for several), as NWB and DANDI want it: 'Last, First'.")
@click.option("--institution", default=None, help="The institution where the session was recorded.")
@click.option("--lab", default=None, help="The lab where the session was recorded.")
def nwb(session, encoded, variants, out, overwrite, progress, keep_nonfinite, experimenters, institution, lab):
    """Export SESSION as an NWB file: taxel readings (TimeSeries), drum and load-cell traces, the trials table, the
    sensor and rig description, and with --encoded the SA/RA spike trains as a Units table (docs/nwb.md)."""
    from pathlib import Path

    from rigctl.storage.encoded import NotEncodedError
    from rigctl.storage.nwb import (
        NwbExportError,
        NwbExportParams,
        check_spike_variants,
        estimate_nwb_bytes,
        export_nwb,
    )
    from rigctl.storage.session import SessionError
    from rigctl.storage.validate import TrialsExcluded

    vlist = [v.strip() for v in variants.split(",") if v.strip()] if variants else None
    if variants is not None and encoded is None:  # was ignored (the export ran without a word)
        raise UsageProblem("--variants chooses among the spike trains of --encoded FILE: give the encoded file too")
    try:
        if encoded is not None:  # before any work: an unknown variant is a usage error
            check_spike_variants(encoded, vlist)
        need = estimate_nwb_bytes(session, encoded)
    except NwbExportError as exc:
        raise UsageProblem(f"--variants: {exc}" if vlist else str(exc)) from None
    except (SessionError, NotEncodedError) as exc:
        raise click.ClickException(str(exc)) from None
    check_output(out, overwrite=overwrite, inputs=(session, encoded), suffixes=(".nwb",), need_bytes=need, kind="nwb")
    import warnings

    try:
        with warnings.catch_warnings(record=True) as caught, bars(show_bars(progress), leave=False) as on_event:
            warnings.simplefilter("always")
            params = NwbExportParams(encoded_path=None if encoded is None else Path(encoded),
                                     variants=tuple(vlist) if vlist else None, overwrite=overwrite,
                                     keep_nonfinite=keep_nonfinite, experimenter=tuple(experimenters),
                                     institution=institution, lab=lab)
            summary = export_nwb(session, out, progress=on_event, params=params)
    except (NwbExportError, SessionError, NotEncodedError) as exc:
        raise click.ClickException(str(exc)) from None
    for w in caught:  # one line each (excluded trials), as rigctl encode shows them
        if issubclass(w.category, TrialsExcluded):
            click.echo(f"warning: {w.message}", err=True)
    units = ", ".join(f"{v}: {n} units, {summary.spikes[v]} spikes" for v, n in summary.units.items())
    click.echo(f"wrote {out}: {summary.n_trials} trials, {summary.n_samples} samples x {summary.n_channels} taxels "
               f"at {summary.rate_hz:g} Hz" + (f"; {units}" if units else ""))


def _splits_writer(encoded: str | None, session: str | None, seed: int, design: dict):
    """``{"splits.json": write}``: the paper's splits of the exported trials (rigctl.analysis.splits): the
    extrapolation cells of ``design`` (``train_speeds_mm_s``, ``train_forces_g``; the paper's when None), or Fig.
    4's tasks for a velocity-profile session (``train_profiles``)."""
    from rigctl.analysis.params import RealtimeParams
    from rigctl.analysis.splits import PAPER_TRAIN_FORCES_G, PAPER_TRAIN_SPEEDS_MM_S, paper_splits
    from rigctl.storage.spike_export import SPLITS_NAME, write_splits

    if encoded is not None:
        from rigctl.storage.encoded import open_encoded

        with open_encoded(encoded) as enc:
            t = enc.trials
            cols: tuple = (t["texture"], t["speed_mm_s"], t["force_g"], t["trial_id"])
            profile: list[str] = [str(p) for p in t["profile"]]
        source = encoded
    else:
        from rigctl.storage.session import open_session
        from rigctl.storage.validate import usable_trials

        assert session is not None
        with open_session(session) as s:
            ids = usable_trials(s).ids
            plan = {int(r["trial_id"]): r for r in s.plan}
            cols = ([plan[i]["texture"] for i in ids], [plan[i]["speed_mm_s"] for i in ids],
                    [plan[i]["force_g"] for i in ids], ids)
            profile = [str(plan[i]["profile"]) for i in ids]
        source = session
    realtime = RealtimeParams(train_profiles=tuple(design["train_profiles"])) if design["train_profiles"] else None
    splits = paper_splits(*cols, seed=seed, profile=profile, realtime=realtime,
                          train_speeds_mm_s=design["train_speeds_mm_s"] or PAPER_TRAIN_SPEEDS_MM_S,
                          train_forces_g=design["train_forces_g"] or PAPER_TRAIN_FORCES_G)
    notes = splits["notes"]
    for note in notes if isinstance(notes, list) else []:
        click.echo(f"note: splits: {note}", err=True)
    return {SPLITS_NAME: lambda path: write_splits(path, splits, source=str(source))}


def _split_design(train_speeds: str | None, train_forces: str | None, train_profiles: str | None) -> dict:
    """The splits' trained cells from the options (None: the paper's)."""
    speeds, forces = comma_floats(train_speeds), comma_floats(train_forces)
    if train_speeds is not None and not speeds:
        raise UsageProblem("--train-speeds: name at least one speed (e.g. 40,60,80)")
    if train_forces is not None and not forces:
        raise UsageProblem("--train-forces: name at least one force (e.g. 250,500)")
    profiles = [p.strip() for p in train_profiles.split(",") if p.strip()] if train_profiles is not None else None
    return {"train_speeds_mm_s": speeds, "train_forces_g": forces, "train_profiles": profiles}


_splits_options = [
    click.option("--splits/--no-splits", default=True, show_default=True,
                 help="Write splits.json beside the files: the paper's tasks (4-fold CV; untrained speed, force, and "
                      "both) as trial ids, drawn as rigctl analyze draws them."),
    click.option("--seed", type=SEED, default=0, show_default=True,
                 help="Seed of the splits' draws (rigctl analyze --seed: its first repetition's split)."),
    click.option("--train-speeds", default=None,
                 help="The splits' trained speeds, mm/s (rigctl analyze --train-speeds; default the paper's 40,60,80)."),
    click.option("--train-forces", default=None,
                 help="The splits' trained forces, g (rigctl analyze --train-forces; default the paper's 250,500)."),
    click.option("--train-profiles", default=None,
                 help="A velocity-profile session's trained profiles (rigctl analyze --train-profiles; default "
                      "slow,medium): the splits are then Fig. 4's tasks."),
]


def _with_splits(f):
    for opt in reversed(_splits_options):
        f = opt(f)
    return f


def _folder_export(out: str, kind: str, overwrite: bool, progress, write, *, value_errors: bool = False):
    """The one shape of a folder export (events, trials): ``out`` checked before any work (an existing folder is
    replaced only when it is rigctl's export of ``kind`` and ``--overwrite`` says so: a usage error otherwise), then
    ``write(on_event)`` under progress bars; a bad --variant is a usage error, a file the export cannot read (or, with
    ``value_errors``, a ValueError of the exporter) one clear line. Returns what ``write`` returns."""
    from rigctl.storage.encoded import NotEncodedError
    from rigctl.storage.export_folder import check_folder_output
    from rigctl.storage.outputs import OutputError
    from rigctl.storage.session import SessionError

    try:
        check_folder_output(out, kind=kind, overwrite=overwrite)
    except OutputError as exc:
        raise UsageProblem(str(exc)) from None
    refused: tuple[type[Exception], ...] = (NotEncodedError, SessionError, OutputError) + \
        ((ValueError,) if value_errors else ())
    try:
        with bars(show_bars(progress), leave=False) as on_event:
            return write(on_event)
    except KeyError as exc:
        raise UsageProblem(f"--variant: {exc.args[0]}") from None
    except refused as exc:
        raise click.ClickException(str(exc)) from None


@export.command("events")
@click.argument("encoded", type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out", type=click.Path(writable=True), required=True,
              help="The folder to write (new; --overwrite replaces only an events export of rigctl's).")
@click.option("--variant", default=None, help="The variant whose spike trains become events (default: original).")
@click.option("--overwrite", is_flag=True, help="Replace an existing events export folder.")
@_with_splits
@progress_option
def events(encoded, out, variant, overwrite, splits, seed, train_speeds, train_forces, train_profiles, progress):
    """Every trial's SA/RA spike trains of ENCODED as events in Tonic's layout: one trial_<id>.npz per trial (a
    structured array x, y, t (us), p (SA 0, RA 1), sensor_size, the labels), with splits.json (docs/guides/spiking-networks.md)."""
    from rigctl.storage.spike_export import EVENTS_KIND, export_events

    design = _split_design(train_speeds, train_forces, train_profiles)
    summary = _folder_export(out, EVENTS_KIND, overwrite, progress, lambda on_event: export_events(
        encoded, out, variant=variant, overwrite=overwrite,
        extra_files=_splits_writer(encoded, None, seed, design) if splits else None, progress=on_event))
    click.echo(f"wrote {out}: {summary.n_trials} trials of {summary.variant}, {summary.n_spikes} events"
               + (", splits.json" if splits else ""))


@export.command("trials")
@click.argument("session", type=click.Path(exists=True, dir_okay=False), required=False)
@click.option("--encoded", type=click.Path(exists=True, dir_okay=False), default=None,
              help="The session's encoded file: its spike trains for --layout per-trial-npz.")
@click.option("--layout", "layouts", type=click.Choice(["per-trial-csv", "per-trial-npz"]), multiple=True,
              required=True, help="per-trial-csv: Data[...].csv taxel readings (needs SESSION); per-trial-npz: "
                                  "SpikeTrains[...].npz spike counts (needs --encoded). Repeatable.")
@click.option("--variant", default=None, help="The variant of the SpikeTrains files (default: original).")
@click.option("--out", "out", type=click.Path(writable=True), required=True,
              help="The folder to write (new; --overwrite replaces only a per-trial export of rigctl's).")
@click.option("--overwrite", is_flag=True, help="Replace an existing per-trial export folder.")
@_with_splits
@progress_option
def trials(session, encoded, layouts, variant, out, overwrite, splits, seed, train_speeds, train_forces,
           train_profiles, progress):
    """A peer lab's per-trial layout: Data[Texture(NNN)][Speed(S)][Force(F)][Trial(k)].csv per trial (a
    velocity-profile session's names add [Profile(name)] before [Trial(k)]; and SpikeTrains[...].npz), with
    rigctl_import.toml to import the CSVs back and splits.json (docs/guides/spiking-networks.md)."""
    from rigctl.storage.spike_export import TRIALS_KIND, export_trials

    if "per-trial-csv" in layouts and session is None:
        raise UsageProblem("--layout per-trial-csv writes the session's readings: give SESSION")
    if "per-trial-npz" in layouts and encoded is None:
        raise UsageProblem("--layout per-trial-npz writes spike trains: give --encoded ENC.h5")
    if variant is not None and encoded is None:
        raise UsageProblem("--variant chooses among the spike trains of --encoded FILE: give the encoded file too")
    design = _split_design(train_speeds, train_forces, train_profiles)
    summary = _folder_export(out, TRIALS_KIND, overwrite, progress, lambda on_event: export_trials(
        out, layouts=layouts, session_path=session, encoded_path=encoded, variant=variant, overwrite=overwrite,
        extra_files=_splits_writer(encoded, session, seed, design) if splits else None, progress=on_event), value_errors=True)
    click.echo(f"wrote {out}: {summary.n_trials} trials, {summary.n_files} files"
               + (", splits.json" if splits else ""))


@export.command("nir")
@click.argument("model", type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out", type=click.Path(dir_okay=False, writable=True), required=True,
              help="The NIR file to write (.nir).")
@click.option("--pcs", "n_pcs", type=click.IntRange(1, 100_000), default=None,
              help="Principal components the readout uses (default: the model's own).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out NIR file.")
def nir(model, out, n_pcs, overwrite):
    """MODEL's readout (a model file of `rigctl analyze --save-model`) as a NIR graph: the window features of a trial
    (each SA train's spike rate and RA train's spike count per window) -> Affine -> one score per texture, the
    largest the prediction; the graph's metadata says how to count the input (docs/guides/spiking-networks.md)."""
    from rigctl.analysis.readout import affine_readout
    from rigctl.storage.model_file import ModelFileError, load_model, read_model_info
    from rigctl.storage.nir_export import NirExportError, write_readout_nir

    check_output(out, overwrite=overwrite, inputs=(model,), suffixes=(".nir",), kind="nir")
    try:
        info = read_model_info(model).get("info", {})
        pipeline = load_model(model)
        readout = affine_readout(pipeline, n_pcs)
    except (ModelFileError, TypeError) as exc:
        raise click.ClickException(str(exc)) from None
    except ValueError as exc:
        raise UsageProblem(f"--pcs: {exc}") from None
    meta = _readout_metadata(pipeline, readout, info)
    try:
        write_readout_nir(out, readout.weight, readout.bias, metadata=meta, overwrite=overwrite)
    except NirExportError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"wrote {out}: {readout.weight.shape[1]} window features -> {readout.weight.shape[0]} textures "
               f"({meta['variant']}, {readout.n_pcs} PCs)")


#: (real-time, speed-scaled) -> how a variant's SA spike rate is counted (rigctl.encoding.features)
_SA_RATE = {
    (False, False): "spikes in the window / window_s",
    (False, True): "spikes in the speed-scaled window / window_s x (trial speed / reference speed): eq. 2",
    (True, False): "spikes in the window / window_s, the trial's last n_windows windows (zero-padded before)",
    (True, True): "spikes in the speed-scaled window / the real-time duration of that window",
}


def _readout_metadata(pipeline, readout, info: dict) -> dict:
    """The NIR graph's metadata: what the input is and how to count it, the classes, where the model came from."""
    from rigctl.core.version import __version__
    from rigctl.storage.encoded import VARIANTS

    features = pipeline[-2] if len(pipeline) > 1 else None
    p = dict(getattr(features, "params_", {}) or {})
    variant = str(getattr(pipeline[-1], "variant", None) or info.get("variant", "?"))
    v = VARIANTS.get(variant)
    realtime, speed_scaled = bool(v and v.realtime), bool(v and v.speed_scaled)
    n_windows = p.get("n_windows_realtime") if realtime else (
        p.get("n_windows_scaled") if speed_scaled else p.get("n_windows_unscaled"))
    n_features = int(readout.weight.shape[1])
    n_trains = n_features // int(n_windows) if n_windows else 0
    return {
        "producer": f"rigctl {__version__} export nir", "variant": variant, "n_pcs": int(readout.n_pcs),
        "classes": [str(c) for c in readout.classes],
        "input": ("train-major window features: for each SA train its spike rate in each window, then (not for "
                  "real-time variants) for each RA train its spike count in each window"),
        "sa_rate": _SA_RATE[(realtime, speed_scaled)],
        "window_s": float(p.get("window_s", 0.1)), "n_windows": int(n_windows or 0),
        "n_sa_trains": n_trains if realtime else n_trains // 2, "n_ra_trains": 0 if realtime else n_trains // 2,
        "time_base": "speed-scaled (eq. 2: spike times x speed / reference speed)" if speed_scaled else "real time",
        "output": "one score per class (metadata classes); the prediction is the class of the largest",
        "model_session": str(info.get("session", "")),
    }

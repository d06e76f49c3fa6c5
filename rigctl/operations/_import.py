"""Importing other labs' recordings as an operator does it, once for ``rigctl import`` (and any other face).

:func:`import_recordings` runs the import (:func:`rigctl.storage.importers.import_recordings`, or the FabricSlide
preset, :func:`rigctl.storage.fabricslide.import_fabricslide`) and returns an :class:`ImportReport`: the summary,
the per-file segmentation table and the outlier warnings as the operator reads them, and a one-line result.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rigctl.core.progress import ProgressCallback

__all__ = ["ImportReport", "IMPORT_PRESETS", "import_recordings", "label_warnings"]

#: plausible label ranges of a sliding texture rig, outside which an import warns (a unit mistaken, e.g. feed rates
#: in mm/min read as mm/s): speeds (mm/s) and forces (g)
PLAUSIBLE_SPEED_MM_S = (1.0, 1000.0)
PLAUSIBLE_FORCE_G = (10.0, 10_000.0)
#: the shortest speed-scaled window (eq. 2: 100 ms of scaled time is 100 ms x 120 / speed of the recording) worth
#: encoding, in model steps of 1 ms: shorter windows hold a spike or two each and Speed Scaled collapses
MIN_SCALED_WINDOW_STEPS = 5

#: the known datasets ``preset`` may name
IMPORT_PRESETS = ("fabricslide",)


@dataclass(frozen=True)
class ImportReport:
    """What an import did.

    summary : the importer's summary (``path``, ``n_trials``, ``samples``, ``rate_hz``, ``n_channels``, ``textures``
        or ``labels``; ``segments`` and ``warnings`` for recordings; ``steps`` the recorded steps)
    table : the per-file segmentation table (file, period, trials, rejected, first start), "" without segmentation
    warnings : one line per outlier file (period or trial count under half / over twice the import's median)
    """

    summary: dict[str, Any]
    table: str = ""
    warnings: list[str] = field(default_factory=list)

    def line(self) -> str:
        """The one-line result: trials, channels, rate, duration, output, textures."""
        s = self.summary
        if "rate_hz" not in s:  # the FabricSlide preset
            return (f"{s['n_trials']} trials, 16 channels at 1000 Hz -> {s['path']} "
                    f"(textures: {', '.join(s['labels'])})")
        return (f"{s['n_trials']} trials, {s['n_channels']} channels at {s['rate_hz']:g} Hz, "
                f"{s['samples'] / s['rate_hz']:.1f} s -> {s['path']} (textures: {', '.join(s['textures'])})")

    def json_summary(self) -> dict[str, Any]:
        """The summary without the recorded steps (what ``--json`` prints)."""
        return {k: v for k, v in self.summary.items() if k != "steps"}


def import_recordings(files: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str], *,
                      preset: str | None = None, overwrite: bool = False, progress: ProgressCallback | None = None,
                      **options: Any) -> ImportReport:
    """Import ``files`` into the session ``out``.

    ``preset="fabricslide"``: ``files`` is one FabricSlide folder (ValueError otherwise); else ``options`` are
    :func:`rigctl.storage.importers.import_recordings`'s (``rate_hz``, ``layout``, ``label_pattern``,
    ``segment_spec``, ``align``, ``pre_ms``, ``nan``, ``mapping``, ...). Raises what the importers raise:
    RecordingImportError / ValueError (one line for the user), FileExistsError, FileNotFoundError.
    """
    if preset is not None:
        if preset not in IMPORT_PRESETS:
            raise ValueError(f"unknown preset {preset!r}; known: {', '.join(IMPORT_PRESETS)}")
        if len(files) != 1:
            raise ValueError(f"--preset {preset} takes one FILES argument: the FabricSlide folder")
        from rigctl.storage.fabricslide import import_fabricslide

        return ImportReport(import_fabricslide(Path(files[0]), Path(out), overwrite=overwrite, progress=progress,
                                               close_gaps=bool(options.get("close_gaps")),  # by name, as for files
                                               clip=bool(options.get("clip"))))
    from rigctl.storage.importers import import_recordings as run
    from rigctl.storage.segmentation import segment_table

    summary = run(files, out, overwrite=overwrite, progress=progress, **options)
    return ImportReport(summary, segment_table(summary["segments"]) if summary["segments"] else "",
                        list(summary["warnings"]) + label_warnings(summary["label_ranges"]))


def label_warnings(ranges: dict[str, Any]) -> list[str]:
    """Lines naming labels (``ranges``: :func:`rigctl.storage.importers.label_ranges`) outside a plausible range
    (:data:`PLAUSIBLE_SPEED_MM_S`, :data:`PLAUSIBLE_FORCE_G`: a unit mistaken) and the speed-scaled windows they give
    (eq. 2: WINDOW_S x 120 mm/s / speed of the recording) when shorter than :data:`MIN_SCALED_WINDOW_STEPS` model
    steps of 1 ms."""
    from rigctl.encoding.speed import REFERENCE_SPEED_MM_S, WINDOW_S

    out = []
    for name, span, (lo, hi), unit, hint in (
            ("speeds", ranges.get("speed_mm_s"), PLAUSIBLE_SPEED_MM_S, "mm/s", "feed rates in mm/min? name the field {speed_mm_min} "
             "(or {speed_m_s}, {speed_cm_s})"),
            ("forces", ranges.get("force_g"), PLAUSIBLE_FORCE_G, "g", "newtons? name the field {force_N} (or {force_mN}, "
             "{force_kg})")):
        if span and (span[0] < lo or span[1] > hi):
            out.append(f"{name} {span[0]:g}-{span[1]:g} {unit} are outside {lo:g}-{hi:g} {unit}, implausible for a "
                       f"sliding texture: {hint}")
    fast = (ranges.get("speed_mm_s") or [0.0, 0.0])[1]
    if fast > 0:
        shortest_ms = 1e3 * WINDOW_S * REFERENCE_SPEED_MM_S / fast
        if shortest_ms < MIN_SCALED_WINDOW_STEPS:
            out.append(f"at {fast:g} mm/s a speed-scaled window is {shortest_ms:.2f} ms of the recording "
                       f"(100 ms x {REFERENCE_SPEED_MM_S:g} / speed, eq. 2): under {MIN_SCALED_WINDOW_STEPS} model "
                       "steps of 1 ms, the Speed Scaled variants would classify from a spike or two per window; "
                       "check the speeds' unit")
    return out


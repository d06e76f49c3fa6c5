"""Cross-validation without leakage: the groups a split must not cut (``rigctl analyze --cv-groups``).

With one continuous recording per texture, a random k-fold split over its cycles puts neighbouring cycles of the
same recording on both sides: the classifier is tested on how well a recording recognises itself (its level, its
drift), not on the texture. Grouped splits hold whole groups out (scikit-learn's ``StratifiedGroupKFold``:
train and test never share a group, each fold's texture mix kept as close to the whole as the groups allow):

- ``recording``: each source recording (an imported trial's file, the encoded ``recording`` column) is one group;
  every texture needs trials in two recordings or more;
- ``session``: each session is one group (an encoded file is made from one session file, so this is refused with
  the reason; kept so a command that names it gets an answer, not a usage error);
- ``block:N``: each recording cut into N time blocks of equal trial counts (in the order the trials start in it,
  ``recording_start_s``; a session recorded here is one recording, its trials in plan order): the first half vs
  the second half for N = 2. Works with one recording per texture.

:func:`cv_groups` gives each trial's group; :func:`one_recording_per_texture` says when a random split can only
measure a recording against itself (``rigctl analyze`` then reports the blocked figure beside the random one).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["GROUPINGS", "parse_cv_groups", "cv_groups", "one_recording_per_texture", "check_groups", "checked_groups",
           "degenerate_groups"]

#: what ``--cv-groups`` may say
GROUPINGS = ("recording", "session", "block:N")


def parse_cv_groups(spec: str) -> tuple[str, int]:
    """``recording`` | ``session`` | ``block:N`` (N >= 2) -> ``(kind, N)`` (N = 0 but for blocks). Raises ValueError
    on anything else."""
    kind, _, n = str(spec).strip().partition(":")
    if kind in ("recording", "session") and not n:
        return kind, 0
    if kind == "block":
        try:
            blocks = int(n)
        except ValueError:
            blocks = 0
        if blocks >= 2:
            return kind, blocks
    raise ValueError(f"--cv-groups {spec!r}: use recording, session or block:N (N >= 2 time blocks per recording)")


def _recordings(fs: Any) -> tuple[np.ndarray, np.ndarray]:
    """Each trial's recording and its start in it (a file without the columns: one recording in trial order)."""
    if fs.recording is not None:
        return fs.recording, fs.recording_start_s
    return np.full(fs.n_trials, "session", dtype=object).astype(str), np.asarray(fs.trial_id, dtype=np.float64)


def cv_groups(fs: Any, spec: str) -> np.ndarray:
    """``(n_trials,)`` str: each trial's group under ``spec`` (:func:`parse_cv_groups`) for the FeatureSet ``fs``.

    Raises ValueError when the file does not carry what ``spec`` groups by (``recording``: no recording column, a
    session recorded here being one recording; ``session``: one session per encoded file)."""
    kind, blocks = parse_cv_groups(spec)
    if kind == "recording":
        if fs.recording is None:
            raise ValueError("--cv-groups recording: the trials carry no source recording (a session recorded here is "
                             "one recording): use --cv-groups block:N")
        return np.asarray(fs.recording, dtype=str)
    if kind == "session":  # an encoded file is made from one session file
        raise ValueError("--cv-groups session: every trial of this file comes from one session (an encoded file is "
                         "made from one session file): use --cv-groups recording or block:N")
    rec, start = _recordings(fs)
    out = np.empty(fs.n_trials, dtype=object)
    for r in np.unique(rec):
        idx = np.flatnonzero(rec == r)
        order = idx[np.lexsort((fs.trial_id[idx], start[idx]))]
        block = (np.arange(order.size) * blocks) // order.size
        out[order] = [f"{r}#{b}" for b in block]
    return out.astype(str)


def one_recording_per_texture(fs: Any) -> bool:
    """True when the trials carry their recordings and every texture's trials come from one recording."""
    if fs.recording is None:
        return False
    pairs = set(zip(fs.texture.tolist(), fs.recording.tolist()))
    return len(pairs) == len(set(fs.texture.tolist()))


def check_groups(texture: np.ndarray, groups: np.ndarray, k: int, spec: str) -> None:
    """ValueError unless every texture has trials in two groups or more and there are at least ``k`` groups (a
    texture in one group could never be both trained and tested), naming the textures that are short."""
    short = sorted(t for t in np.unique(texture) if np.unique(groups[texture == t]).size < 2)
    if short:
        raise ValueError(f"--cv-groups {spec}: {', '.join(short[:8])}{' ...' if len(short) > 8 else ''} "
                         f"{'has' if len(short) == 1 else 'have'} all trials in one group, so no split can train and "
                         "test it: use --cv-groups block:N (time blocks of each recording)")
    n = np.unique(groups).size
    if n < k:
        raise ValueError(f"--cv-groups {spec}: {n} groups cannot fill {k} folds")


def degenerate_groups(fs: Any, spec: str, groups: np.ndarray) -> str | None:
    """One line when ``groups`` (:func:`cv_groups` of ``spec``) are not what ``spec`` asks (issue 77 item 7): with
    ``block:N``, recordings of fewer than N trials cannot be cut into N blocks (one file per trial: each trial is
    its own block, which is ``--cv-groups recording``), said with how many; None when the grouping is as asked."""
    kind, blocks = parse_cv_groups(spec)
    if kind != "block":
        return None
    rec, _ = _recordings(fs)
    names, sizes = np.unique(rec, return_counts=True)
    short = int(np.count_nonzero(sizes < blocks))
    if not short:
        return None
    whole = " (one file per trial?): every block is a whole recording, as --cv-groups recording holds them out" \
        if short == names.size and int(sizes.max()) == 1 else ": their blocks are fewer and hold whole recordings"
    return (f"--cv-groups {spec}: {short} of {names.size} recordings hold fewer than {blocks} trials{whole}; "
            f"{np.unique(groups).size} groups for {len(groups)} trials, not {blocks} time blocks of each recording")


def checked_groups(fs: Any, spec: str, k: int) -> tuple[np.ndarray, str | None]:
    """:func:`cv_groups` of ``spec`` checked for ``k`` folds (:func:`check_groups`: ValueError) and the line of
    :func:`degenerate_groups` (None when the grouping is as asked)."""
    groups = cv_groups(fs, spec)
    check_groups(fs.texture, groups, k, spec)
    return groups, degenerate_groups(fs, spec, groups)

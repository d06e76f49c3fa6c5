"""Soak: a long simulated session with faults injected on both links and kill -9 of the recording process.

Three parts run side by side for ``--minutes`` (default 60), each on real ptys:

- **taxel link**: a virtual Uno streaming a counting source (rigctl.simulation.counting: every recorded frame can be
  checked) through a :class:`~rigctl.simulation.fault_proxy.FaultProxy` (bit flips, lost, inserted and garbage
  bytes, stalls, link cuts and restores) to a :class:`~rigctl.devices.taxel_stream.TaxelStream`, in segments of
  ~20 s captures. Per segment: frames the board sent, recorded, counted lost (sequence gaps; the estimate over a
  reconnect), stale, CRC errors, and every recorded frame checked intact (bad-CRC frames recorded: must be 0).
  Segments without a cut must account exactly: ``sent == recorded + counted lost + stale`` (silent losses: must be 0).
- **Modbus link**: a virtual Mega behind a FaultProxy (noise both ways, spells of answers later than the client's
  timeout, cuts) and a :class:`~rigctl.devices.drum.DrumClient` reading registers with known values and writing and
  reading back a scratch register: every value returned must be the register's own (wrong values taken: must be 0);
  failed requests (DrumError) are counted as survived when the client works again afterwards.
- **kill -9**: ``rigctl acquire PROTOCOL --sim --resume`` in a subprocess killed at a random moment, again and again;
  after each kill plain h5py opens the file, every finished trial is readable and unchanged since it finished
  (finished trials lost: must be 0), and the last run of each session completes the plan with each trial recorded
  once (duplicates: must be 0). The temporary port folders of killed runs must be gone at the end (the commands
  make them in a folder of the soak's own, their ``TMPDIR``; the next run's simulated rig removes a killed one's).

Prints the figures (``--json PATH`` writes them too) and exits 1 if any must-be-0 figure is not 0.

Usage: python benchmarks/bench_soak.py [--minutes 60] [--seed 1] [--json PATH] [--work DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from rigctl.devices.drum import DrumClient
from rigctl.devices.errors import DrumError
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.devices.wire import HoldingRegister as HR
from rigctl.simulation.counting import CountingSource, intact_frames
from rigctl.simulation.fault_proxy import TO_BOARD, TO_HOST, FaultProxy, FaultRates
from rigctl.simulation.model import RigModel
from rigctl.simulation.pty import TEMP_PREFIX
from rigctl.simulation.virtual_mega import VirtualMega
from rigctl.simulation.virtual_uno import VirtualUno
from rigctl.storage.journal import lock_path

RIGCTL = [sys.executable, "-c", "from rigctl.cli import main; main()"]

KILL_PROTOCOL = """\
name = "soak"
textures = ["A", "B", "C"]
speeds_mm_s = [80, 120]
forces_g = [400]
trials_per_condition = 2
duration_s = 0.5

[settle]
settle_time_ms = 50
"""

TAXEL_NOISE = FaultRates(flip=2e-5, drop=1e-5, insert=1e-5, garbage=5e-6, garbage_max=100)
MODBUS_NOISE = FaultRates(flip=2e-3, drop=1e-3, insert=1e-3, garbage=3e-4, garbage_max=16)
MODBUS_LATE = FaultRates(flip=2e-3, drop=1e-3, insert=1e-3, garbage=3e-4, garbage_max=16, delay_s=0.5)


def _wait(cond, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


# ------------------------------------------------------------------------------------------------------- taxel link
def taxel_soak(stop_at: float, seed: int, work: Path, out: dict) -> None:
    rng = random.Random(seed)
    f = out.setdefault("taxel", dict(segments=0, segments_with_cut=0, frames_sent=0, frames_recorded=0,
                                     frames_counted_lost=0, stale_frames=0, crc_errors=0, bad_frames_recorded=0,
                                     silent_losses=0, overcount_across_cuts=0, link_cuts_survived=0,
                                     stalls=0, bytes_flipped=0, bytes_dropped=0, bytes_inserted=0, garbage_bursts=0))
    uno = VirtualUno(work / "taxel", reset_delay_s=0.1)
    uno.run_paced(CountingSource())
    proxy = FaultProxy(uno.path, work / "taxel-proxy", seed=seed).start()
    try:
        with TaxelStream(proxy.path) as stream:
            while time.monotonic() < stop_at:
                seg_s = rng.uniform(10, 30)
                cut = rng.random() < 0.4
                st0, sent0, bdrop0 = stream.stats, uno.frames_sent, uno.frames_dropped
                stream.begin_capture()
                stream.start()
                proxy.set_rates(TO_HOST, TAXEL_NOISE)
                t_seg = time.monotonic()
                if cut:
                    proxy.schedule(rng.uniform(2, seg_s - 5), proxy.cut)
                if rng.random() < 0.5:
                    proxy.schedule(rng.uniform(1, seg_s - 2), proxy.stall, rng.uniform(0.05, 0.5), TO_HOST)
                    f["stalls"] += 1
                while time.monotonic() - t_seg < seg_s:
                    time.sleep(0.1)
                    if not proxy.stats().connected and time.monotonic() - t_seg > 1:
                        time.sleep(rng.uniform(0.3, 1.5))  # unplugged for a while, then plugged back
                        proxy.restore()
                if not proxy.stats().connected:
                    proxy.restore()
                proxy.set_rates(TO_HOST, FaultRates())
                reconnected = _wait(lambda: stream.stats.connected, 10)
                n = stream.stats.frames
                _wait(lambda: stream.stats.frames >= n + 200, 10)  # clean frames: the last losses are seen
                stream.stop()
                _wait(lambda: not uno.streaming, 5)
                proxy.wait_idle()
                sent = uno.frames_sent - sent0 + (uno.frames_dropped - bdrop0)

                def counted():
                    s = stream.stats
                    return (s.frames - st0.frames) + (s.dropped - st0.dropped) + (s.stale_frames - st0.stale_frames)

                _wait(lambda: counted() >= sent, 10)
                time.sleep(0.1)
                cap = stream.end_capture()
                s = stream.stats
                recorded = s.frames - st0.frames
                lost = s.dropped - st0.dropped
                stale = s.stale_frames - st0.stale_frames
                f["segments"] += 1
                f["frames_sent"] += sent
                f["frames_recorded"] += recorded
                f["frames_counted_lost"] += lost
                f["stale_frames"] += stale
                f["crc_errors"] += s.crc_errors - st0.crc_errors
                f["bad_frames_recorded"] += int((~intact_frames(cap.samples)).sum()) if len(cap) else 0
                gap = sent - (recorded + lost + stale)
                if cut:
                    f["segments_with_cut"] += 1
                    f["link_cuts_survived"] += int(reconnected and s.reconnects > st0.reconnects)
                    # lost frames across a reconnect are estimated from the time gap: an over-count can hide a
                    # silent loss in the same segment, so only an under-count is reported as silent
                    f["silent_losses"] += max(gap, 0)
                    f["overcount_across_cuts"] += max(-gap, 0)
                else:
                    f["silent_losses"] += abs(gap)  # exact: sequence numbers count every lost frame
        ps = proxy.stats().to_host
        f.update(bytes_flipped=ps.flipped, bytes_dropped=ps.dropped, bytes_inserted=ps.inserted,
                 garbage_bursts=ps.garbage_bursts)
    finally:
        proxy.close()
        uno.close()


# ------------------------------------------------------------------------------------------------------ Modbus link
def modbus_soak(stop_at: float, seed: int, work: Path, out: dict) -> None:
    rng = random.Random(seed + 1)
    f = out.setdefault("modbus", dict(requests=0, answered=0, wrong_values=0, failed_requests=0,
                                      failures_recovered=0, stale_responses_discarded=0, timeouts=0, fences=0,
                                      link_cuts_survived=0, late_spells=0, bytes_mangled=0))
    mega = VirtualMega(RigModel(seed=seed), work / "drum", eeprom_path=work / "eeprom.json").start()
    proxy = FaultProxy(mega.path, work / "drum-proxy", seed=seed + 1).start()
    fixed = {HR.FORCE_TOLERANCE_G: 15, HR.WATCHDOG_MS: 1000, HR.RAMP_DURATION_MS: 3000}
    scratch, scratch_values = HR.SETTLE_TIME_MS, {300}  # the values it may hold (one after a confirmed answer)
    pending_failure = False
    try:
        drum = DrumClient(proxy.path, timeout_s=0.3, retries=2, poll_s=0.02).open()
        proxy.set_rates(TO_HOST, MODBUS_NOISE)
        proxy.set_rates(TO_BOARD, MODBUS_NOISE)
        next_spell = time.monotonic() + rng.uniform(5, 20)
        next_cut = time.monotonic() + rng.uniform(30, 90)
        last_scheduled = 0.0  # when the last scheduled proxy action (end of a late spell, a restore) fires
        while time.monotonic() < stop_at:
            now = time.monotonic()
            if now > next_spell:
                proxy.set_rates(TO_HOST, MODBUS_LATE)
                after = rng.uniform(0.5, 2.0)
                proxy.schedule(after, proxy.set_rates, TO_HOST, MODBUS_NOISE)
                last_scheduled = max(last_scheduled, now + after)
                f["late_spells"] += 1
                next_spell = now + rng.uniform(5, 20)
            if now > next_cut:
                proxy.cut()
                after = rng.uniform(0.5, 3.0)
                proxy.schedule(after, proxy.restore)
                last_scheduled = max(last_scheduled, now + after)
                next_cut = now + rng.uniform(30, 90)
                f["link_cuts_survived"] += 1  # counted back below if the client never works again
            f["requests"] += 1
            try:
                if rng.random() < 0.3:
                    value = rng.randrange(100, 1000)
                    try:
                        drum.write_holding(scratch, value)
                        scratch_values = {value}
                    except DrumError:
                        scratch_values = scratch_values | {value}  # carried out or not: either value is right
                        raise
                    asked = scratch
                    got, allowed = drum.read_holding(scratch), scratch_values
                    scratch_values = {got} if got in allowed else scratch_values
                else:
                    reg = asked = rng.choice(list(fixed))
                    got, allowed = drum.read_holding(reg), {fixed[reg]}
                f["answered"] += 1
                if got not in allowed:
                    f["wrong_values"] += 1
                    out.setdefault("wrong_value_details", []).append({  # what a developer needs to find the cause
                        "t_s": round(time.monotonic() - stop_at, 3), "register": int(asked), "got": got,
                        "allowed": sorted(allowed), "rx": drum._rx.hex(), "timeouts": drum.timeouts,
                        "stale": drum.stale_responses, "fences": drum.fences})
                if pending_failure:
                    f["failures_recovered"] += 1
                    pending_failure = False
            except DrumError:
                f["failed_requests"] += 1
                pending_failure = True
                time.sleep(0.1)  # as a host would before trying again (a cut port fails at once)
        # a clean link at the end: once every scheduled action has fired (a late spell's end set after this would
        # bring the noise back), no faults, the link restored, nothing held in the proxy
        while time.monotonic() < last_scheduled + 0.1:
            time.sleep(0.05)
        proxy.set_rates(TO_HOST, FaultRates())
        proxy.set_rates(TO_BOARD, FaultRates())
        if not proxy.stats().connected:
            proxy.restore()
        proxy.wait_idle()
        ok, deadline = False, time.monotonic() + 10.0
        while time.monotonic() < deadline:  # the client works again: the first answer it gets is right
            try:
                ok = drum.read_holding(HR.FORCE_TOLERANCE_G) == 15
                break
            except DrumError:  # (a loaded host: an answer later than the client's timeout) try again, as a host
                time.sleep(0.2)
        if pending_failure and ok:
            f["failures_recovered"] += 1
        if not ok:
            f["link_cuts_survived"] = 0
        f["works_at_the_end"] = ok
        f.update(stale_responses_discarded=drum.stale_responses, timeouts=drum.timeouts, fences=drum.fences)
        ps = proxy.stats()
        f["bytes_mangled"] = sum(c.flipped + c.dropped + c.inserted for c in (ps.to_host, ps.to_board))
        drum.close()
    finally:
        proxy.close()
        mega.close()


# ------------------------------------------------------------------------------------------------------ kill -9
def _finished(path: Path) -> dict[int, str]:
    """Plain h5py: trial id -> digest of its taxel readings, for every trial the plan marks complete."""
    with h5py.File(path, "r") as fh:
        status = fh["plan"]["status"][()]
        out = {}
        for tid in np.flatnonzero(status == 1):
            g = fh[f"trials/{int(tid):06d}"]
            taxels = g["taxels"][()]
            if taxels.shape[0] != int(g.attrs.get("n_samples", taxels.shape[0])):
                raise AssertionError(f"trial {tid}: {taxels.shape[0]} samples, attribute says {g.attrs['n_samples']}")
            out[int(tid)] = hashlib.sha1(taxels.tobytes()).hexdigest()
        return out


def _wait_released(path: Path, timeout_s: float = 30.0) -> bool:
    """Wait until no process holds the session's writer lock (``<name>.lock``, dropped as the killed writer dies: a
    command run through a launcher dies just after its client) nor the lock on the file itself (the writer's commit
    helper outlives it by design until its in-place writes are done). False after ``timeout_s``."""
    import fcntl

    def free() -> bool:
        for p in (lock_path(path), path):
            try:
                fd = os.open(p, os.O_RDONLY)
            except FileNotFoundError:
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return False
            finally:
                os.close(fd)  # drops the shared lock too
        return True

    return _wait(free, timeout_s)


#: each run is killed this long after its start (s, drawn uniformly): shorter than a session, or no run is killed
KILL_AFTER_S = (1.0, 10.0)
KILL_GRACE_S = 120.0  # how long past its length a soak's kill -9 part may go on for its first kill and session


def kill_soak(stop_at: float, seed: int, work: Path, out: dict, protocol: str = KILL_PROTOCOL,
              rigctl: Sequence[str] = RIGCTL, kill_after_s: tuple[float, float] = KILL_AFTER_S) -> None:
    rng = random.Random(seed + 2)
    f = out.setdefault("kill", dict(kills=0, sessions_completed=0, trials_finished=0, finished_trials_lost=0,
                                    finished_trials_changed=0, duplicates=0, unreadable_after_kill=0,
                                    runs_failed=0, tmp_leftovers=0, tmp_left_by_kills=0))
    proto = work / "soak.toml"
    proto.write_text(protocol)
    tmp = work / "tmp"  # the commands' temporary folder: every port folder left in it at the end is a leftover
    tmp.mkdir()
    env = dict(os.environ, RIGCTL_CONFIG=str(work / "rig.json"), TMPDIR=str(tmp))
    # a short soak on a busy machine may end before it has killed one run that had made its simulated rig (each kill
    # is drawn from kill_after_s after a start that can take seconds) or before a session ran to its end: it goes on, at most
    # KILL_GRACE_S past its length, until it has both (a soak that never gets them fails on its figures, not a hang)
    grace_until = stop_at + KILL_GRACE_S

    def go_on_killing() -> bool:
        now = time.monotonic()
        return now < stop_at or (f["tmp_left_by_kills"] == 0 and now < grace_until)

    session = 0
    while go_on_killing() or (f["sessions_completed"] == 0 and time.monotonic() < grace_until):
        path = work / f"kill-{session}.h5"
        finished: dict[int, str] = {}
        while True:
            cmd = [*rigctl, "acquire", str(proto), "--sim", "--out", str(path), "--quiet"]
            if path.exists():
                cmd.append("--resume")
            proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            kill = go_on_killing()  # the last run of the soak is let finish
            try:
                proc.wait(timeout=rng.uniform(*kill_after_s) if kill else 300)
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
                f["kills"] += 1
                # the port folders the killed run's simulated rig left (for the next run's to remove)
                f["tmp_left_by_kills"] += sum(1 for _ in tmp.glob(f"{TEMP_PREFIX}*"))
            if not _wait_released(path):
                f["runs_failed"] += 1
                out.setdefault("kill_errors", []).append(f"{path.name}: still locked 30 s after the kill")
                break
            err = proc.stderr.read().decode(errors="replace")
            if not path.exists():
                continue  # killed before the file was made
            try:
                now = _finished(path)
            except Exception as exc:  # noqa: BLE001 - a finding, not a crash of the soak
                f["unreadable_after_kill"] += 1
                out.setdefault("kill_errors", []).append(f"{path.name}: {exc}")
                break
            f["finished_trials_lost"] += len(set(finished) - set(now))
            f["finished_trials_changed"] += sum(1 for t in finished if t in now and now[t] != finished[t])
            finished = now
            if proc.returncode == 0:
                with h5py.File(path, "r") as fh:
                    names = list(fh["trials"])
                    n_plan = len(fh["plan"])
                f["duplicates"] += len(names) - len(set(names)) + max(0, len(names) - n_plan)
                if len(finished) == n_plan:
                    f["sessions_completed"] += 1
                    f["trials_finished"] += len(finished)
                break
            if proc.returncode != -signal.SIGKILL:
                f["runs_failed"] += 1
                out.setdefault("kill_errors", []).append(err.strip().splitlines()[-1:] or [f"rc {proc.returncode}"])
                break
        session += 1
        if path.exists():
            path.unlink()
    f["tmp_leftovers"] = sum(1 for _ in tmp.glob(f"{TEMP_PREFIX}*"))


# ------------------------------------------------------------------------------------------------------ main
MUST_BE_ZERO = [("taxel", "silent_losses"), ("taxel", "bad_frames_recorded"), ("modbus", "wrong_values"),
                ("kill", "finished_trials_lost"), ("kill", "finished_trials_changed"), ("kill", "duplicates"),
                ("kill", "unreadable_after_kill"), ("kill", "runs_failed"), ("kill", "tmp_leftovers")]


def run(minutes: float, seed: int, work: Path, *, kill_protocol: str = KILL_PROTOCOL,
        rigctl: Sequence[str] = RIGCTL, kill_after_s: tuple[float, float] = KILL_AFTER_S) -> dict:
    """Run the three parts side by side for ``minutes``; returns the figures (``errors``: parts that crashed).
    ``kill_protocol``: the protocol (TOML text) the kill -9 part records again and again; the last session of the
    soak runs to its end after ``minutes``, so a short soak gives a short one. ``rigctl``: the argv prefix of the
    ``rigctl`` command the kill -9 part runs and kills (a fresh interpreter; the tests give their preloaded one,
    tests/launcher.py, whose client's death kills its command with SIGKILL). ``kill_after_s``: the range each run's
    kill is drawn from (s after its start; keep it shorter than one session of ``kill_protocol``)."""
    stop_at = time.monotonic() + minutes * 60
    out: dict = {"minutes": minutes, "seed": seed, "errors": []}
    t0 = time.time()

    def part(fn, sub, *args):
        (work / sub).mkdir(parents=True, exist_ok=True)
        try:
            fn(stop_at, seed, work / sub, out, *args)
        except Exception:  # noqa: BLE001 - reported as a failure of the soak
            out["errors"].append(f"{fn.__name__}: {traceback.format_exc()}")

    threads = [threading.Thread(target=part, args=(fn, fn.__name__, *args), daemon=True)
               for fn, args in ((taxel_soak, ()), (modbus_soak, ()), (kill_soak, (kill_protocol, rigctl, kill_after_s)))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    out["wall_s"] = round(time.time() - t0, 1)
    out["load_average"] = os.getloadavg()
    out["failures"] = [f"{a}.{b} = {out.get(a, {}).get(b)}" for a, b in MUST_BE_ZERO
                       if out.get(a, {}).get(b, 0) != 0] + (["a part crashed"] if out["errors"] else [])
    if out.get("modbus", {}).get("works_at_the_end") is False:
        out["failures"].append("modbus: the client did not work again on a clean link")
    return out


def main(argv=None) -> int:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # its own line per failed reopen of a cut port
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="how long each part runs (default 60)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file (new file)")
    ap.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one)")
    a = ap.parse_args(argv)
    if a.json is not None and a.json.exists():
        ap.error(f"{a.json} exists: give a new file")
    with tempfile.TemporaryDirectory(prefix="rigctl-soak-") as tmp:
        out = run(a.minutes, a.seed, a.work or Path(tmp))
    text = json.dumps(out, indent=1, default=str)
    print(text)
    if a.json is not None:
        a.json.write_text(text)
    print("soak: " + ("PASS" if not out["failures"] else "FAIL: " + "; ".join(out["failures"])), file=sys.stderr)
    return 0 if not out["failures"] else 1


if __name__ == "__main__":
    sys.exit(main())

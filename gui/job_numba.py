"""Imported into the analysis jobs' fork server (last of :data:`rigctl_gui.workers.JOB_PRELOAD`, never into the app):
sets up numba's CPU target once in the server (its runtime and its registries of implementations: the imports and
set-up numba does before it loads or compiles its first kernel in a process), so each job forked from the server
starts with it done instead of doing it again (measured: ~0.35 CPU-s a job). Nothing is compiled here and no thread
is started (the server forks the jobs; numba's parallel kernels start their threads in the job that runs them)."""

from __future__ import annotations

from numba.core.registry import cpu_target

cpu_target.target_context.refresh()  # refreshes the typing context too

"""Simulation campaigns: many runs, batched and spread over workers with joblib.

A campaign is a list of :class:`~sim.api.Request`. Runs of similar length are
grouped into batches (one vectorised simulation each) and the batches are
dispatched through ``joblib.Parallel``; any joblib backend works, so a Ray or
Dask cluster takes a sweep larger than one machine with
``joblib.parallel_config(backend="ray")`` (``--backend ray``) and nothing else
changes. Results are deterministic for a seed whatever the backend or the
number of workers: each run's randomness comes from its own seed, derived from
the campaign seed and the run's index.

Workers end with the campaign's process: a worker that is its child (loky,
multiprocessing) is bound to it when it starts (loky initializer) and again at
each batch (any backend): on Linux the kernel sends it SIGKILL the moment its
parent ends (``PR_SET_PDEATHSIG``), elsewhere a watchdog thread ends it within
:data:`WATCHDOG_S`. An interrupt (KeyboardInterrupt) in the parent makes joblib
kill and join the workers before it propagates. Workers on other machines (Ray,
Dask) are left to their cluster's cancellation.

Preset ``paper`` is the data set of the paper: the ten manoeuvres of Table I,
each at four speeds spread over its Table I range, on roads of friction
1.0, 0.7, 0.5, 0.3 and 0.2 (dry asphalt to ice), 20 Hz, about 45,000 samples.
"""

from __future__ import annotations

import json
import os
import signal
import threading
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from sim.api import Request, SimRun, simulate_many
from sim.driver import Plan
from sim.engine import OUTCOMES
from sim.manoeuvres import MANOEUVRES, build_plan

PAPER_MU = (1.0, 0.7, 0.5, 0.3, 0.2)
PAPER_SPEEDS_PER_MANOEUVRE = 4
PAPER_MANOEUVRES = tuple(n for n in MANOEUVRES if n not in ("magny-cours", "circuit"))


def _speed_friction_grid(seed: int, speeds_per_manoeuvre: int, mus: Sequence[float]) -> list[Request]:
    """Each Table I manoeuvre at ``speeds_per_manoeuvre`` speeds spread over its range, each on every friction of
    ``mus``, in that order; each run's seed drawn from ``seed``."""
    seeds = np.random.SeedSequence(seed).generate_state(len(PAPER_MANOEUVRES) * len(mus) * speeds_per_manoeuvre)
    requests = []
    i = 0
    for name in PAPER_MANOEUVRES:
        lo, hi = MANOEUVRES[name].speed_kmh
        for speed in np.linspace(lo, hi, speeds_per_manoeuvre):
            for mu in mus:
                requests.append(Request(name, float(round(speed, 1)), mu, int(seeds[i])))
                i += 1
    return requests


def paper_preset(seed: int = 0) -> list[Request]:
    """The paper's Table I campaign (200 runs), deterministic for ``seed``."""
    return _speed_friction_grid(seed, PAPER_SPEEDS_PER_MANOEUVRE, PAPER_MU)


def smoke_preset(seed: int = 0) -> list[Request]:
    """A small campaign (one mid-range speed per manoeuvre, dry and wet) for tests and demos."""
    seeds = np.random.SeedSequence(seed).generate_state(2 * len(PAPER_MANOEUVRES))
    out = []
    for i, name in enumerate(PAPER_MANOEUVRES):
        lo, hi = MANOEUVRES[name].speed_kmh
        for j, mu in enumerate((1.0, 0.5)):
            out.append(Request(name, float(round((lo + hi) / 2, 1)), mu, int(seeds[2 * i + j])))
    return out


#: frictions of the ``wide`` preset (dry, wet, low grip), each at every speed of every manoeuvre
WIDE_MU = (1.0, 0.7, 0.4)
#: speeds per manoeuvre of the ``wide`` preset, spread over its Table I range
WIDE_SPEEDS_PER_MANOEUVRE = 3


def wide_preset(seed: int = 0) -> list[Request]:
    """Each Table I manoeuvre at three speeds over its range on three frictions (90 runs, about 21,000 samples):
    between ``smoke`` and ``paper``. The diagnosis' retraining campaign: an estimator trained on it errs little
    enough on held-out runs that what a calibration changes shows (``tools/gain_oracle.py``)."""
    return _speed_friction_grid(seed, WIDE_SPEEDS_PER_MANOEUVRE, WIDE_MU)


def tiny_preset(seed: int = 0) -> list[Request]:
    """Four short runs (tests, quick looks)."""
    seeds = np.random.SeedSequence(seed).generate_state(4)
    picks = (("steering-pulse", 50.0, 1.0), ("single-sine", 60.0, 0.5), ("brake-accel", 60.0, 0.3),
             ("double-lane-change", 60.0, 0.7))
    return [Request(n, v, mu, int(s)) for (n, v, mu), s in zip(picks, seeds, strict=True)]


#: frictions of the ``circuits`` preset, each on every random circuit (dry asphalt to packed snow)
CIRCUITS_MU = (1.0, 0.7, 0.45, 0.25)
#: top speeds (km/h) of the ``circuits`` preset: drawn uniformly in this range per run
CIRCUITS_SPEED_KMH = (110.0, 230.0)
#: random circuits of the ``circuits`` preset
CIRCUITS_COUNT = 8


def circuits_preset(seed: int = 0) -> list[Request]:
    """Track driving for training: one lap of each of :data:`CIRCUITS_COUNT` random circuits
    (:mod:`sim.randomtrack`, ``random:SEED``) on each friction of :data:`CIRCUITS_MU`, at a random
    top speed; deterministic for ``seed``. No surveyed circuit is used, so every real circuit
    (Magny-Cours and the development circuits) stays unseen by a model trained on it."""
    ss = np.random.SeedSequence([seed, 0xC1C])
    track_seeds = ss.generate_state(CIRCUITS_COUNT)
    run_seeds = ss.spawn(1)[0].generate_state(CIRCUITS_COUNT * len(CIRCUITS_MU))
    rng = np.random.default_rng(ss.spawn(2)[1])
    out = []
    for i, track_seed in enumerate(track_seeds):
        for j, mu in enumerate(CIRCUITS_MU):
            speed = float(round(rng.uniform(*CIRCUITS_SPEED_KMH)))
            out.append(Request("circuit", speed, mu, int(run_seeds[i * len(CIRCUITS_MU) + j]),
                               track=f"random:{int(track_seed)}", laps=1))
    return out


#: the placard (nominal) inflation pressure of the catalogue car (gauge, bar)
NOMINAL_PRESSURE_BAR = 2.2
#: the range (bar) a driver sets a car's tyres to, uniformly: well under- to well over-inflated
SET_PRESSURE_BAR = (1.6, 3.0)
#: one wheel's spread about the set pressure (bar, standard deviation: gauge and fill tolerance, temperature)
WHEEL_SPREAD_BAR = 0.07
#: share of runs with one wheel leaking, and how much it lost (bar, uniform)
LEAK_SHARE, LEAK_BAR = 0.25, (0.2, 0.6)
#: every drawn pressure lies in this range (bar; the tyre model's valid range PRESMIN-PRESMAX is 1.5-3.5)
PRESSURE_LIMITS_BAR = (1.5, 3.4)


def draw_pressures(requests: Sequence[Request], seed: int = 0) -> list[Request]:
    """The runs with each one's four tyre pressures drawn (gauge, bar, to 0.01): a set pressure uniform in
    :data:`SET_PRESSURE_BAR`, each wheel about it with :data:`WHEEL_SPREAD_BAR`, and in :data:`LEAK_SHARE` of the
    runs one wheel (at random) down by :data:`LEAK_BAR`, so left and right are not always equal; clipped to
    :data:`PRESSURE_LIMITS_BAR`. Deterministic for ``seed``, drawn apart from every other randomness of the runs
    (their manoeuvres and sensors are those of the same campaign without the draw)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7135]))
    n = len(requests)
    p = rng.uniform(*SET_PRESSURE_BAR, size=(n, 1)) + rng.normal(0.0, WHEEL_SPREAD_BAR, size=(n, 4))
    leak = rng.random(n) < LEAK_SHARE
    wheel = rng.integers(0, 4, size=n)
    loss = rng.uniform(*LEAK_BAR, size=n)
    p[np.arange(n), wheel] -= np.where(leak, loss, 0.0)
    p = np.round(np.clip(p, *PRESSURE_LIMITS_BAR), 2)
    return [replace(r, pressures_bar=tuple(float(x) for x in row)) for r, row in zip(requests, p, strict=True)]


PRESETS: dict[str, Callable[[int], list[Request]]] = {
    "paper": paper_preset, "smoke": smoke_preset, "wide": wide_preset, "tiny": tiny_preset,
    "circuits": circuits_preset,
}


#: polling period (s) of the watchdog that ends a worker whose parent is gone (where prctl is missing)
WATCHDOG_S = 0.2
_PR_SET_PDEATHSIG = 1
_bound_to: int | None = None


def _set_pdeathsig(sig: int) -> bool:
    """Ask the Linux kernel to send ``sig`` to this process when its parent ends."""
    import ctypes
    import ctypes.util

    if not os.uname().sysname == "Linux":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watchdog(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        threading.Event().wait(WATCHDOG_S)
    os._exit(1)


def bind_to_parent(parent_pid: int) -> None:
    """Make the calling worker process end when the campaign's process ``parent_pid`` ends.

    Idempotent. Does nothing in the campaign's own process (sequential or
    threading backends) or in a process that is not its child (a worker of a
    cluster). On Linux the kernel delivers SIGKILL at the parent's death;
    elsewhere a daemon thread polls the parent every :data:`WATCHDOG_S` s. (The
    kernel ties the signal to the parent's thread that started the worker: loky
    starts its workers from threads that live as long as its executor.)
    """
    global _bound_to
    if _bound_to == parent_pid or os.getpid() == parent_pid or os.getppid() != parent_pid:
        return
    _bound_to = parent_pid
    if not _set_pdeathsig(signal.SIGKILL):
        threading.Thread(target=_watchdog, args=(parent_pid,), daemon=True, name="campaign-watchdog").start()
    if os.getppid() != parent_pid:  # the parent ended before the binding took effect
        os._exit(1)


def _loky_initializer(parent_pid: int) -> None:
    """Start of a loky worker (always a child of the campaign's process): bind it, or
    end it at once if the campaign's process ended while it was starting."""
    if os.getppid() != parent_pid:
        os._exit(1)
    bind_to_parent(parent_pid)


def _batches(plans: Sequence[Plan], n_batches: int) -> list[list[int]]:
    """Group run indices into batches of similar duration (less padding per batch)."""
    # longest batches first, so the short ones fill the workers at the end
    order = np.argsort([p.duration_s for p in plans], kind="stable")[::-1]
    return [list(map(int, chunk)) for chunk in np.array_split(order, n_batches) if len(chunk)]


def _run_batch(requests: Sequence[Request], plans: Sequence[Plan], params: Mapping[str, Any],
               writer: Callable[[SimRun], Any] | None, parent_pid: int):
    bind_to_parent(parent_pid)
    runs = simulate_many(requests, params, plans=plans)
    if writer is None:
        return runs
    return [writer(r) for r in runs]


def run_campaign(
    requests: Sequence[Request],
    params: Mapping[str, Any],
    *,
    n_jobs: int = -1,
    batch_size: int = 25,
    writer: Callable[[SimRun], Any] | None = None,
    progress: bool = True,
    backend: str | None = None,
) -> list[Any]:
    """Simulate ``requests``; returns per request the SimRun, or ``writer(run)`` if given.

    Args:
        requests: the runs.
        params: the car (shared by all runs).
        n_jobs: joblib workers (-1: all cores).
        batch_size: runs per vectorised batch (bigger batches amortise numpy's
            per-call overhead; 30-60 is the sweet spot on a small machine).
        writer: called in the worker on each finished run (e.g. to write its file);
            its return value replaces the run in the result (keeps memory low).
        progress: show a tqdm bar on stderr.
        backend: joblib backend name (None: joblib's default, loky; ``ray`` and ``dask``: see
            :func:`_backend_config`).
    """
    from joblib import Parallel, delayed
    from tqdm import tqdm

    if not requests:
        return []
    # plans are built once, here (the FMVSS 126 amplitude needs a simulated test per car),
    # and shipped to the workers with their requests
    plans = [build_plan(r.manoeuvre, r.speed_kmh, r.mu, r.seed, params, **r.options()) for r in requests]
    n_batches = max(1, int(np.ceil(len(requests) / batch_size)))
    groups = _batches(plans, n_batches)
    results: list[Any] = [None] * len(requests)
    me = os.getpid()
    with _backend_config(backend, me, n_jobs):
        from joblib.parallel import get_active_backend

        # a backend that cannot stream results (joblib's Ray backend) returns them all at the end
        streams = bool(getattr(get_active_backend()[0], "supports_return_generator", False))
        par = Parallel(n_jobs=n_jobs, return_as="generator" if streams else "list")
        jobs = (delayed(_run_batch)([requests[i] for i in g], [plans[i] for i in g], params, writer, me)
                for g in groups)
        outputs = par(jobs)
        try:
            with tqdm(total=len(requests), unit="run", disable=not progress, desc="simulating") as bar:
                for g, out in zip(groups, outputs, strict=True):
                    for i, item in zip(g, out, strict=True):
                        results[i] = item
                    bar.update(len(g))
        finally:
            if streams:
                outputs.close()  # on an interrupt: joblib kills and joins the workers now
    return results


#: the warnings filter (``PYTHONWARNINGS`` syntax) :func:`_quiet_resource_tracker` gives loky's processes
QUIET_TRACKER = "ignore:resource_tracker:UserWarning"


#: campaigns running in this process under :func:`_quiet_resource_tracker`, and ``PYTHONWARNINGS`` before the first
_quiet_depth = 0
_quiet_had: str | None = None
_quiet_lock = threading.Lock()


@contextmanager
def _quiet_resource_tracker() -> Iterator[None]:
    """loky's resource tracker (a process of its own, started with the first workers, inheriting this process's
    environment) warns at its exit of the semaphores of workers that were killed: on an error or an interrupt the
    campaign kills them on purpose, and the one line the command prints is all the user should see. While any
    campaign of this process runs, ``PYTHONWARNINGS`` (any filters already set, and :data:`QUIET_TRACKER`) has the
    processes it starts ignore those ``resource_tracker: ...`` warnings; the variable is restored when the last
    running campaign ends (campaigns in threads overlap; a tracker started meanwhile keeps the filter, later
    processes do not get it)."""
    global _quiet_depth, _quiet_had
    with _quiet_lock:
        if _quiet_depth == 0:
            _quiet_had = os.environ.get("PYTHONWARNINGS")
            if QUIET_TRACKER not in (_quiet_had or "").split(","):
                os.environ["PYTHONWARNINGS"] = ",".join(x for x in (_quiet_had, QUIET_TRACKER) if x)
        _quiet_depth += 1
    try:
        yield
    finally:
        with _quiet_lock:
            _quiet_depth -= 1
            if _quiet_depth == 0:
                if _quiet_had is None:
                    os.environ.pop("PYTHONWARNINGS", None)
                else:
                    os.environ["PYTHONWARNINGS"] = _quiet_had


@contextmanager
def _backend_config(backend: str | None, parent_pid: int, n_jobs: int = -1) -> Iterator[None]:
    """joblib configuration of a campaign: loky (joblib's default) with workers bound
    to the campaign's process from their start; ``ray`` registered with joblib, joining the
    cluster named by ``RAY_ADDRESS`` or starting a local one; ``dask`` on the cluster of the
    current client or of ``DASK_SCHEDULER_ADDRESS``, else a local one of ``n_jobs`` workers
    (closed at the end); any other backend as named. Workers of a cluster write their runs
    into the campaign's directory: it must be on a file system they share."""
    from joblib import parallel_config
    from joblib.parallel import get_active_backend

    default_is_loky = type(get_active_backend()[0]).__name__ == "LokyBackend"
    if backend == "loky" or (backend is None and default_is_loky):
        with _quiet_resource_tracker(), parallel_config(backend="loky", initializer=_loky_initializer,
                                                        initargs=(parent_pid,)):
            yield
    elif backend == "ray":
        import ray
        from ray.util.joblib import register_ray

        register_ray()
        started = not ray.is_initialized()
        if started:
            ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False)
        try:
            with parallel_config(backend="ray"):
                yield
        finally:
            if started:
                ray.shutdown()
    elif backend == "dask":
        with _dask_client(n_jobs), parallel_config(backend="dask"):
            yield
    else:
        with parallel_config(backend=backend) if backend else nullcontext():
            yield


@contextmanager
def bound_workers(backend: str | None = None, n_jobs: int = -1) -> Iterator[None]:
    """joblib configured as a campaign's (:func:`_backend_config`) for work other than a campaign's (the
    diagnosis' re-simulations): local workers (loky) bound to this process from their start, so that they end
    with it (SIGKILL at its death on Linux, else within :data:`WATCHDOG_S`), even while running a task."""
    with _backend_config(backend, os.getpid(), n_jobs):
        yield


@contextmanager
def _dask_client(n_jobs: int) -> Iterator[None]:
    """The current Dask client, a client of ``DASK_SCHEDULER_ADDRESS``, or a local cluster of ``n_jobs``
    single-threaded worker processes (all cores for -1) that ends with the campaign."""
    import dask
    from distributed import Client, get_client

    try:
        get_client()
    except ValueError:  # no client yet: one is made below
        pass
    else:
        yield
        return
    address = dask.config.get("scheduler-address", None)
    workers = (os.cpu_count() or 1) if n_jobs < 1 else n_jobs
    client = Client(address) if address else Client(n_workers=workers, threads_per_worker=1, processes=True,
                                                    dashboard_address=None)
    try:
        yield
    finally:
        client.close()


def manifest_entry(run: SimRun, path: Path, samples: int, duration_s: float) -> dict[str, Any]:
    """What a campaign's manifest says about one written run.

    ``outcome`` says how the run ended (:meth:`sim.engine.BatchResult.outcome`):
    ``"completed"`` or, for a run cut short, ``"spun"``, ``"stopped"`` or ``"off-track"``,
    with the time ``at_s`` (s) it ended and the plan's ``planned_s``, so a short run
    never passes for a complete one. A run with a planned distance (circuits, the double
    lane change) adds ``driven_m`` and ``planned_m`` along its path; one whose time ran out
    short of it is ``"behind-plan"`` (a whole recording of what the car did, not the lap).
    """
    request = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(run.request).items()
               if k not in ("track", "laps", "pressures_bar") or v is not None}
    return {
        "file": path.name,
        **request,
        "samples": samples,
        "duration_s": duration_s,
        "outcome": dict(run.outcome),
        "label": json.loads(json.dumps(run.plan.label, default=float)),
    }


def outcome_tally(outcomes: Iterable[Mapping[str, Any]]) -> str:
    """The runs' outcomes (manifest ``outcome`` entries) in a few words: ``"all completed"``, or
    how many did not complete as planned, by status (:data:`sim.engine.OUTCOMES` order), e.g.
    ``"17 not completed as planned: 15 spun, 2 behind-plan"``."""
    counts = Counter(str(o.get("status", "completed")) for o in outcomes)
    counts.pop("completed", None)
    if not counts:
        return "all completed"
    order = sorted(counts, key=lambda s: (OUTCOMES.index(s) if s in OUTCOMES else len(OUTCOMES), s))
    return (f"{sum(counts.values())} not completed as planned: "
            + ", ".join(f"{counts[s]} {s}" for s in order))

"""Where the diagnosis' batches run: in this process, on local joblib workers, or on a Ray cluster.

``backend="loky"`` (the default) spreads the batches over ``n_jobs`` local
worker processes; ``backend="ray"`` hands them to joblib's Ray backend, so the
same command runs a fleet's test days on a Ray cluster (``ray.init`` joins the
cluster named by ``RAY_ADDRESS``, or starts a local one). Ray is an optional
extra (``pip install 'virtsensor[distributed]'``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from virtsensor.errors import UserError

BACKENDS = ("loky", "ray")


def check_backend(backend: str) -> None:
    """UserError unless ``backend`` is known and importable."""
    if backend not in BACKENDS:
        raise UserError(f"--backend {backend!r}: one of {', '.join(BACKENDS)}")
    if backend == "ray":
        try:
            import ray  # noqa: F401
            from ray.util.joblib import register_ray  # noqa: F401
        except ImportError:
            raise UserError("--backend ray needs Ray: pip install 'virtsensor[distributed]'") from None


def run_parallel(fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]], *, n_jobs: int = 1,
                 backend: str = "loky") -> list[Any]:
    """``[fn(*args) for args in calls]``, in order, on ``n_jobs`` workers of ``backend``.

    One call or one worker (loky) runs in this process. Local workers end with this process, as a campaign's
    (:func:`sim.campaign.bound_workers`): killed or interrupted, it leaves none running."""
    if backend == "loky" and (n_jobs == 1 or len(calls) <= 1):
        return [fn(*a) for a in calls]
    from joblib import Parallel, delayed, parallel_backend

    if backend == "ray":
        check_backend(backend)
        import ray
        from ray.util.joblib import register_ray

        register_ray()
        if not ray.is_initialized():
            ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False)
        with parallel_backend("ray"):
            return list(Parallel(n_jobs=n_jobs)(delayed(fn)(*a) for a in calls))
    from sim.campaign import bound_workers

    with bound_workers(backend, n_jobs):  # (the workers end with this process, even in the middle of a call)
        return list(Parallel(n_jobs=n_jobs)(delayed(fn)(*a) for a in calls))

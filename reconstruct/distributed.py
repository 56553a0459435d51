"""Band work on a Dask cluster (``ps-lab reconstruct --scheduler``, ``ps-lab batch``).

Dask (``dask.distributed``) is an optional dependency (``make demo`` and ``make test`` install it;
else ``.venv/bin/pip install -e '.[distributed]'`` in the clone);
:mod:`ps_lab.reconstruct.pipeline` loads this module only when a scheduler is given, so a plain
``ps-lab reconstruct`` never imports Dask.

The design (``docs/scale.md``, "On a Dask cluster"): the client plans the bands and creates the
staging file, full size, inside the staged output folder. **Pass 1** runs one task per group of
lights: the worker reads those frames from the dataset itself (a shared filesystem is assumed),
and writes their mask pixels into the staging file (:func:`ps_lab.io.bands.stage_lights`),
returning only its rows of the noise sample. The client estimates the whole-image noise level from
that sample, exactly as in one process. **Each solve pass** runs one task per band: the worker
reads the band's block from the staging file, solves it with one thread and returns a
:class:`~ps_lab.reconstruct._bands.BandResult` (float32 normals, albedo and corruption of the
band's mask pixels, or the light-refinement sums). The client writes the outputs through the same
staged folder as always. Every task is a pure function of its arguments and the files, so Dask
can run it again on another worker when one dies.
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ps_lab.errors import ClusterError
from ps_lab.io.bands import Band, ObservationStore, stage_lights
from ps_lab.io.coding import float_coding, observe_rule
from ps_lab.io.coded_frames import frame_coding
from ps_lab.io.dataset import DatasetHeader, reference_exposure
from ps_lab.io.truth import open_normal_gt
from ps_lab.reconstruct._bands import BandResult, band_truth, solve_band

try:  # the optional dependency: the error below names the extra to install
    import distributed as _dask
    from dask import config as dask_config
except ImportError:  # pragma: no cover - exercised by the missing-Dask test
    _dask = None

log = logging.getLogger(__name__)

INSTALL_HINT = (
    "Dask is not installed: in the ps-lab clone, run .venv/bin/pip install -e '.[distributed]'"
)
# Bands per worker at least (for load balance and a finer progress bar), memory budget permitting.
BANDS_PER_WORKER = 4
# Stage tasks per worker when a dark frame makes each task re-read it (else one light per task).
STAGE_TASKS_PER_WORKER = 4


def require_dask() -> Any:
    """The ``distributed`` module, or :class:`ClusterError` saying how to install it."""
    if _dask is None:
        raise ClusterError(INSTALL_HINT)
    return _dask


@contextmanager
def connect(address: str, *, timeout: float | None = None) -> Iterator[Any]:
    """A Dask client connected to the scheduler at ``address``, closed afterwards.

    Raises
    ------
    ClusterError
        Dask missing, or no scheduler answering at ``address`` within ``timeout`` seconds
        (default: Dask's ``distributed.comm.timeouts.connect``, 30 s).

    """
    dask = require_dask()
    probe_scheduler(address)
    with _quiet_dask():
        try:
            limit = {} if timeout is None else {"timeout": timeout}
            client = dask.Client(address, set_as_default=False, **limit)
        except Exception as exc:  # noqa: BLE001 - whatever answered is not a usable scheduler
            _abandon_client(exc, dask.Client)
            detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            raise ClusterError(
                f"--scheduler {address}: cannot reach a Dask scheduler there ({detail})"
            ) from None
        log.info("Dask scheduler %s, dashboard %s", address, client.dashboard_link)
        try:
            yield client
        finally:
            client.close()


#: Seconds a TCP scheduler address has to accept a connection (and, plain TCP, to send Dask's
#: handshake) before Dask is asked to connect.
PROBE_SECONDS = 3.0
# Largest first message length taken for a Dask handshake (a real one is a few hundred bytes).
_MAX_HANDSHAKE = 1 << 24


def probe_scheduler(address: str, timeout: float = PROBE_SECONDS) -> None:
    """Refuse, in one line and within ``timeout`` seconds, an address no scheduler can be at.

    The address is parsed first (``tcp://HOST:PORT``; a port that is not a number is refused
    before Dask, whose client would otherwise hang in its destructor); a TCP address must then
    accept a connection within ``timeout`` (Dask itself retries for 30 s). Other transports
    are left to Dask.

    Raises
    ------
    ClusterError
        Naming ``--scheduler`` and the address.
    """
    dask = require_dask()
    addressing = dask.comm.addressing
    try:
        scheme, location = addressing.parse_address(address, strict=False)
        known = scheme in dask.comm.registry.backends
        host, port = addressing.parse_host_port(location) if scheme in ("tcp", "tls") else ("", 0)
    except (ValueError, TypeError) as exc:
        raise ClusterError(
            f"--scheduler {address}: not a Dask scheduler address ({exc}); expected "
            "tcp://HOST:PORT"
        ) from None
    if not known:
        raise ClusterError(
            f"--scheduler {address}: unknown transport {scheme!r}; expected tcp://HOST:PORT"
        )
    if scheme not in ("tcp", "tls"):
        return
    if not 0 < port < 65536:
        raise ClusterError(f"--scheduler {address}: port {port} is not a TCP port (1-65535)")
    try:
        connection = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise ClusterError(
            f"--scheduler {address}: no Dask scheduler answers there ({reason}); start one with "
            "`dask scheduler`, or leave --scheduler out for a local cluster"
        ) from None
    if scheme == "tcp":
        # A scheduler sends its handshake as soon as it accepts; its first 8 bytes are a message
        # length. Another service is silent (Dask's client would then wait forever) or says
        # something else (Dask would read a length of exabytes).
        with connection:
            try:
                first = connection.recv(8, socket.MSG_WAITALL)
            except OSError:
                first = None
        if not first or len(first) < 8 or struct.unpack("<Q", first)[0] > _MAX_HANDSHAKE:
            said = "nothing" if not first else f"{first[:8]!r}"
            raise ClusterError(
                f"--scheduler {address}: something answers there but it is not a Dask scheduler "
                f"(it sent {said} within {timeout:g} s instead of Dask's handshake)"
            )
    else:
        connection.close()


def _abandon_client(exc: BaseException, client_type: type) -> None:
    """Mark the half-made client of a failed ``Client(...)`` closed, and stop its event loop.

    Its destructor would otherwise wait 60 s on a connection that never came and then print a
    traceback ("Exception ignored in Client.__del__") after the error line.
    """
    tb = exc.__traceback__
    while tb is not None:
        candidate = tb.tb_frame.f_locals.get("self")
        if isinstance(candidate, client_type):
            candidate.status = "closed"
            runner = getattr(candidate, "_loop_runner", None)
            try:
                if runner is not None:
                    runner.stop()
            except Exception:  # noqa: BLE001 - best effort, the error line matters
                pass
            return
        tb = tb.tb_next


@contextmanager
def _quiet_dask() -> Iterator[None]:
    """Keep Dask's own log records (tracebacks of a lost connection) off the terminal.

    What goes wrong reaches the user as one :class:`ClusterError` line; ``-vv`` shows them.
    """
    logger = logging.getLogger("distributed")
    if logging.getLogger().isEnabledFor(logging.DEBUG):
        yield
        return
    silent = logging.NullHandler()
    propagate, handlers = logger.propagate, logger.handlers[:]
    # Dask's own stderr handler too (its CRITICAL records would print over the one line).
    logger.handlers = [silent]
    logger.propagate = False
    try:
        yield
    finally:
        logger.propagate = propagate
        logger.handlers = handlers


@contextmanager
def local_cluster(workers: int) -> Iterator[Any]:
    """A Dask cluster of ``workers`` processes (one thread each) on this machine, and its client.

    The embedded default of ``ps-lab batch``: nothing to install or start. The dashboard takes a
    free port (logged at ``-v``); worker logs are silenced (errors come back through the futures).
    """
    dask = require_dask()
    # The workers' scratch space is this run's own (Dask's default stays behind in TMPDIR).
    with tempfile.TemporaryDirectory(prefix="ps-lab-dask-", ignore_cleanup_errors=True) as scratch:
        with dask_config.set({"temporary-directory": scratch}), _quiet_dask(), dask.LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.CRITICAL,
            local_directory=scratch,
        ) as cluster, dask.Client(cluster, set_as_default=False) as client:
            log.info(
                "local Dask cluster of %d workers, dashboard %s", workers, client.dashboard_link
            )
            yield client


def completed(
    client: Any, futures: Sequence[Any], *, lost: str = "nothing was written"
) -> Iterator[tuple[Any, Any, Exception | None]]:
    """Yield ``(future, result, exception)`` as the futures complete.

    ``exception`` is the task's own (then ``result`` is None). A lost scheduler raises
    :class:`ClusterError` (its message ends with ``lost``); on that, any other error or Ctrl-C,
    the futures not yet done are cancelled.
    """
    dask = require_dask()
    try:
        for future in dask.as_completed(futures, loop=client.loop):
            try:
                yield future, future.result(), None
            except (dask.client.FutureCancelledError, dask.comm.CommClosedError) as exc:
                raise ClusterError(
                    f"lost the Dask scheduler at {client.scheduler.address} "
                    f"({type(exc).__name__}); {lost}"
                ) from None
            except RuntimeError as exc:
                if "deserializ" not in str(exc):
                    yield future, None, exc
                    continue
                raise ClusterError(
                    "the Dask scheduler or a worker cannot load ps-lab: start `dask scheduler` "
                    "and `dask worker` from ps-lab's environment"
                ) from None
            except Exception as exc:  # noqa: BLE001 - the caller decides (raise, or report)
                yield future, None, exc
    except BaseException:
        client.cancel(list(futures))
        raise


def gather(client: Any, futures: Sequence[Any]) -> Iterator[Any]:
    """Yield the futures' results as they complete; a task's exception is raised as it is.

    A :class:`ps_lab.errors.PsLabError` raised in a task (a corrupt frame, say) thus reaches the
    command line as its usual one line; the remaining futures are cancelled.
    """
    for _, result, exc in completed(client, futures):
        if exc is not None:
            raise exc
        yield result


class DaskBands:
    """The band executor on a Dask cluster (same methods as ``_bands.LocalBands``)."""

    name = "dask"

    def __init__(self, client: Any) -> None:
        self.client = client
        self.token = os.urandom(4).hex()  # task keys of this run, readable on the dashboard
        self.passes = 0

    def _workers(self) -> int:
        return max(len(self.client.scheduler_info().get("workers", {})), 1)

    def band_pixels(self, budget_pixels: int, pixels: int, keep_plan: bool) -> int:
        """Most mask pixels per band: the memory budget's, and small enough to feed every worker.

        At least :data:`BANDS_PER_WORKER` bands per worker, unless ``keep_plan``: a result that
        depends on the band plan (R-PCA's low-rank model is fitted per band; light refinement adds
        its sums band by band, so the rounding follows the plan) keeps the in-process plan, and so
        the in-process result to the last bit.
        """
        if keep_plan:
            return budget_pixels
        return max(1, min(budget_pixels, -(-pixels // (BANDS_PER_WORKER * self._workers()))))

    def stage(
        self,
        header: DatasetHeader,
        mask: np.ndarray,
        bands: list[Band],
        *,
        channel: str,
        shadow_threshold: float | None,
        folder: Path,
        in_memory: bool,
        sample_pixels: int,
        progress: Callable[[int], None],
        colours: int = 0,
        coding=None,
        decoders: int | None = None,
    ) -> ObservationStore:
        """Pass 1 as tasks: workers stage groups of lights into a file in ``folder``.

        ``in_memory`` is ignored: the workers need a file; the workers store linear float32
        (``coding`` gives the frames' channels).
        """
        n = len(header.names)
        store = ObservationStore(
            bands, n, mask, folder=folder, sample_pixels=sample_pixels, colours=colours,
            coding=float_coding((coding or frame_coding(header.plan)).channels),
            rule=observe_rule(header.light_intensities, channel, shadow_threshold),
        )
        try:
            per_task = 1
            if header.plan.dark_files:  # each task averages the dark frame again
                per_task = max(1, -(-n // (STAGE_TASKS_PER_WORKER * self._workers())))
            exposure = reference_exposure(header.plan)
            futures = [
                self.client.submit(
                    _stage_task,
                    header,
                    bands,
                    lights,
                    str(store.path),
                    common_exposure=exposure,
                    channel=channel,
                    shadow_threshold=shadow_threshold,
                    sample_pixels=sample_pixels,
                    colours=colours,
                    channels=store.coding.channels,
                    key=f"ps-lab-stage-{self.token}-{lights[0]}",
                )
                for lights in (list(range(a, min(a + per_task, n))) for a in range(0, n, per_task))
            ]
            for lights, observations, valid, colour in gather(self.client, futures):
                store.sample_observations[lights] = observations
                store.sample_valid[lights] = valid
                store.sample_colour[lights] = colour
                progress(len(lights))
        except BaseException:
            store.close()
            raise
        return store

    def solve(
        self,
        store: ObservationStore,
        header: DatasetHeader,
        vectors: np.ndarray,
        *,
        method: str,
        parameters: dict[str, Any],
        final: bool,
        truth,
        advance: Callable[..., None],
        label: str,
        black: np.ndarray | None = None,
    ) -> Iterator[BandResult]:
        """One solve pass as tasks, one per non-empty band; results in completion order."""
        self.passes += 1
        futures = [
            self.client.submit(
                _solve_task,
                header,
                str(store.path),
                store.bands,
                band.index,
                vectors,
                method=method,
                parameters=parameters,
                final=final,
                with_truth=truth is not None,
                black=black,
                colours=store.colours,
                coding=store.coding,
                rule=store.rule,
                key=f"ps-lab-band-{self.token}-{self.passes}-{band.index}",
            )
            for band in store.bands
            if band.pixel_count
        ]
        count = len(store.bands)
        for result in gather(self.client, futures):
            band = store.bands[result.index]
            advance(band.pixel_count, description=f"{label}: band {band.index + 1}/{count}")
            yield result


# --- the tasks (run on the workers) ----------------------------------------------------------

_MASKS: dict[tuple, np.ndarray] = {}


def worker_mask(header: DatasetHeader) -> np.ndarray:
    """The dataset's mask, read once per worker process (kept for the latest dataset only)."""
    file = header.mask_file
    key = (str(header.root), str(file), file.stat().st_mtime_ns if file else 0, header.shape)
    mask = _MASKS.get(key)
    if mask is None:
        mask = header.read_mask()
        mask.setflags(write=False)
        _MASKS.clear()
        _MASKS[key] = mask
    return mask


def _stage_task(header, bands, lights, path, **kwargs) -> tuple[list[int], np.ndarray, ...]:
    observations, valid, colour = stage_lights(
        header, worker_mask(header), bands, lights, Path(path), **kwargs
    )
    return lights, observations, valid, colour


def _solve_task(
    header, path, bands, index, vectors, *, method, parameters, final, with_truth, black=None,
    colours=0, coding=None, rule=None,
) -> BandResult:
    band = bands[index]
    mask = worker_mask(header)
    with ObservationStore(
        bands, len(header.names), mask, sample_pixels=0, path=Path(path), colours=colours,
        coding=coding, rule=rule, threads=1,
    ) as store:
        observations, valid, colour = store.observe(band, colour=final)
    truth = open_normal_gt(header.root, mask.shape) if with_truth else None
    return solve_band(
        observations,
        valid,
        index,
        vectors,
        method=method,
        parameters=parameters,
        threads=1,  # a worker runs as many tasks at once as it has threads
        final=final,
        truth_rows=None if truth is None else band_truth(truth, mask, band),
        black=black,
        colour=colour,
    )

"""Executors of a suite's runs: worker processes on this machine, or Ray tasks on a cluster.

An executor runs :class:`~mitsuba_active.bench.Job` s and advances a progress
bar as each finishes; the suite's records and report are the driver's either
way. With Ray, each run is a task that asks for :attr:`RayOptions.cpus_per_run`
CPUs (and :attr:`RayOptions.gpus_per_run` of a GPU on ``cuda_ad_rgb``); a task
whose worker dies is retried, and a run that raises is not. A worker that sees
the suite folder (shared storage) writes its run there, as a local worker does;
one that does not gets the run's inputs (the scene's files, a planner file of
the user's own, what the run folder holds so far) from the driver and sends
the run folder back, which the driver then puts in place whole.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import socket
import sys
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import mitsuba as mi
from tqdm import tqdm

from .console import mitsuba_log_as_warnings, show_warning
from .errors import UserError
from .imageio_utils import replaced_folder
from .planners.base import is_planner_file
from .scene import referenced_files

#: The executors, and what each one runs the suite's runs on.
EXECUTORS = {"local": "worker processes on this machine (--workers)",
             "ray": "Ray tasks, on a local Ray instance or a cluster (--address)"}
#: Where a Ray worker writes its run: ``auto``, in the suite folder when it sees
#: that folder (shared storage), else back through the driver; ``driver``, always through the driver.
STORAGE = ("auto", "driver")
#: The extra that installs Ray, as the error that misses it says.
RAY_EXTRA = "pip install 'mitsuba-active[ray]'"
#: Seconds to wait for a cluster's address to answer before Ray is asked to join it.
CONNECT_TIMEOUT = 5.0
#: Environment variables that a Ray task gets from the driver (the variant, the ground-truth cache).
FORWARDED_ENV = ("MITSUBA_ACTIVE_VARIANT", "MITSUBA_ACTIVE_CACHE", "DRJIT_LIBLLVM_PATH")


@dataclass
class RayOptions:
    """How ``bench --executor ray`` runs a suite (each field is a command-line option of ``bench``)."""
    address: str | None = field(default=None, metadata={
        "help": "Ray cluster to run on: 'auto' (the one this machine joined with `ray start`) or HOST:PORT "
                "[a Ray instance of this machine's own, for this suite only]."})
    cpus_per_run: float = field(default=1.0, metadata={
        "help": "CPUs each run asks Ray for (its Dr.Jit threads, rounded up)."})
    gpus_per_run: float | None = field(default=None, metadata={
        "help": "Share of a GPU each run asks Ray for [0.25 on cuda_ad_rgb, 0 otherwise]."})
    retries: int = field(default=3, metadata={
        "help": "Times a run whose worker died (a node lost, a process killed) is run again."})
    storage: str = field(default="auto", metadata={
        "help": "auto: workers that see the suite folder (shared storage) write their runs there, others send "
                "them to this machine; driver: every run comes back to this machine."})

    def check(self) -> None:
        """UserError on a value Ray cannot run with."""
        if self.address not in (None, "auto") and _host_port(self.address) is None:
            raise UserError(f"--address takes 'auto' or HOST:PORT of a Ray cluster's head, got '{self.address}'")
        if not (isinstance(self.cpus_per_run, (int, float)) and self.cpus_per_run > 0):
            raise UserError(f"--cpus-per-run must be more than 0, got {self.cpus_per_run}")
        if self.gpus_per_run is not None and not (isinstance(self.gpus_per_run, (int, float))
                                                  and 0 <= self.gpus_per_run <= 1):
            raise UserError(f"--gpus-per-run is a share of one GPU, from 0 to 1, got {self.gpus_per_run}")
        if not (isinstance(self.retries, int) and self.retries >= 0):
            raise UserError(f"--retries must be a whole number of 0 or more, got {self.retries}")
        if self.storage not in STORAGE:
            raise UserError(f"--storage is one of {', '.join(STORAGE)}, got {self.storage!r}")


#: Share of a GPU per run on ``cuda_ad_rgb`` unless set: four runs share a GPU.
GPU_SHARE = 0.25
#: The command-line names of :class:`RayOptions`' fields.
RAY_OPTION_NAMES = {f.name: "--" + f.name.replace("_", "-") for f in fields(RayOptions)}


# ---------------------------------------------------------------------------
# Local worker processes
# ---------------------------------------------------------------------------

def run_local(jobs: list, workers: int, bar, run_job) -> None:
    """Run the jobs here (one worker) or in up to ``workers`` fresh processes (Dr.Jit
    must not be forked once initialised), which share the cores; Ctrl-C stops them all and is raised here.

    ``run_job(job, threads)`` runs one job and returns its status (a module-level
    function: the workers import it by name)."""
    if workers == 1:
        for job in jobs:
            bar.set_postfix_str(f"{job.scene}/{job.planner}/{job.seed}")
            run_job(job)
            bar.update()
        return

    workers = max(1, min(workers, len(jobs)))  # a worker without a job would only start and stop
    threads = max(1, (os.cpu_count() or 1) // workers)
    # The workers are made with Ctrl-C ignored, a disposition they keep through
    # their start, so that one pressed while they import prints no tracebacks.
    # (Only a Ctrl-C within the few milliseconds of making them is lost.)
    main_thread = threading.current_thread() is threading.main_thread()
    pool = None
    try:
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN) if main_thread else None
        try:
            pool = mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(os.getpid(),))
        finally:
            if main_thread:  # None: a handler not set from Python, which cannot be put back
                signal.signal(signal.SIGINT, signal.default_int_handler if handler is None else handler)
        for status in pool.imap_unordered(_run_job_star, [(run_job, j, threads) for j in jobs]):
            bar.set_postfix_str(status["job"])
            bar.update()
        pool.close()
        pool.join()
    except BaseException:  # Ctrl-C, or a failed job
        if pool is not None:
            _stop_pool(pool)
        raise


def _stop_pool(pool, patience: float = 10.0) -> None:
    """Stop the workers (SIGTERM: they exit through their clean-up) and wait
    for them; should that not end within ``patience`` seconds (a worker or
    the pool's own bookkeeping stuck), end them outright, so that an
    interrupted suite always stops."""
    stopper = threading.Thread(target=pool.terminate, daemon=True)
    stopper.start()
    stopper.join(patience)
    if stopper.is_alive():
        for child in mp.active_children():
            child.kill()
        stopper.join(patience)


def _init_worker(parent: int):
    """Ctrl-C is the parent's to handle: it stops the workers (SIGTERM), and a
    worker stopped in a job exits through its ``finally`` blocks, so no
    temporary file is left (an idle one exits at once). A worker whose parent
    is gone (killed outright) stops itself the same way. tqdm's lock is a
    thread lock here: its default, a multiprocessing lock, would be reported
    as leaked when a worker stops."""
    def stop(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one stop; its clean-up is not cut short
        if not _worker_busy:
            # Idle, or already exiting (a failed job ends the pool): nothing to
            # clean up, and an exception raised inside the interpreter's exit
            # handlers would only be printed as a traceback.
            os._exit(1)
        raise SystemExit(1)

    def stop_again(info):
        if signal.getsignal(signal.SIGTERM) is not signal.SIG_IGN:  # not stopping
            sys.__unraisablehook__(info)
        elif isinstance(info.exc_value, SystemExit):
            # A stop that lands in a callback Python runs on its own (a weakref's, during garbage
            # collection) is printed and dropped there: deliver it again, to the job's own code.
            signal.signal(signal.SIGTERM, stop)
            # From another thread, a moment later: sent from here, the stop would be raised inside this hook.
            later = threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGTERM))
            later.daemon = True
            later.start()
        # Otherwise the finaliser of an object the stop cut short in its making: nothing to report.

    def watch_parent():
        while os.getppid() == parent:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGTERM)

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, stop)
    sys.unraisablehook = stop_again
    threading.Thread(target=watch_parent, daemon=True).start()
    tqdm.set_lock(threading.RLock())
    _show_warnings_as_lines()


def _show_warnings_as_lines() -> None:
    """Warnings, Mitsuba's too, as the command line shows them: plain lines on stderr."""
    warnings.showwarning = show_warning
    if not _WORKER_LOGGING._exit_callbacks:  # once per process
        _WORKER_LOGGING.enter_context(mitsuba_log_as_warnings())


#: Keeps the worker's Mitsuba logging (see :func:`_init_worker`) for its lifetime.
_WORKER_LOGGING = contextlib.ExitStack()


#: Whether this worker process is running a job (see :func:`_init_worker`).
_worker_busy = False


def _run_job_star(args):
    run_job, *rest = args
    global _worker_busy
    _worker_busy = True
    try:
        return run_job(*rest)
    finally:
        _worker_busy = False


# ---------------------------------------------------------------------------
# Ray
# ---------------------------------------------------------------------------

def import_ray():
    """The ``ray`` module; UserError naming the extra that installs it when it is missing."""
    try:
        import ray
    except ImportError:
        raise UserError(f"--executor ray needs Ray: {RAY_EXTRA}") from None
    return ray


def _host_port(address) -> tuple[str, int] | None:
    """``(host, port)`` of an address ``HOST:PORT`` (or ``ray://HOST:PORT``), else None."""
    host, sep, port = str(address).removeprefix("ray://").rpartition(":")
    return (host, int(port)) if sep and host and port.isdigit() else None


def prepare_ray(options: RayOptions) -> None:
    """UserError at once, before a suite authors anything, when Ray is missing,
    an option is bad or ``--address`` does not answer (Ray itself would retry for minutes)."""
    options.check()
    import_ray()
    if options.address in (None, "auto"):
        return
    try:
        socket.create_connection(_host_port(options.address), timeout=CONNECT_TIMEOUT).close()
    except OSError as exc:
        raise UserError(f"no Ray cluster answers at {options.address} ({exc.strerror or exc}); start one with "
                        "`ray start --head` there, or leave --address out") from None


@contextlib.contextmanager
def ray_session(options: RayOptions):
    """Ray, joined to ``options.address`` (or a local instance of this
    machine's own) for the block; a Ray this call started is stopped after
    it, one the caller started is left running."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    env = {k: os.environ[k] for k in FORWARDED_ENV if k in os.environ}
    try:
        ray.init(address=options.address, include_dashboard=False, log_to_driver=True,
                 logging_level="error", runtime_env={"env_vars": env} if env else None)
    except ConnectionError as exc:
        raise UserError(f"cannot join a Ray cluster at {options.address}: {str(exc).splitlines()[0]}") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def run_ray(jobs: list, options: RayOptions, bar, run_job) -> None:
    """Run the jobs as Ray tasks and write what the workers send back; the first
    run that fails (or whose worker dies more than ``options.retries`` times)
    cancels the others and is raised here, as is Ctrl-C. ``run_job``: as
    :func:`run_local` takes it."""
    gpus = options.gpus_per_run
    if gpus is None:
        gpus = GPU_SHARE if (mi.variant() or "").startswith("cuda") else 0.0
    with ray_session(options) as ray:
        exceptions = ray.exceptions
        threads = max(1, int(-(-options.cpus_per_run // 1)))
        task = ray.remote(_ray_task).options(num_cpus=options.cpus_per_run, num_gpus=gpus,
                                             max_retries=options.retries, retry_exceptions=False)
        bundles: dict = {}  # the inputs of the runs of one scene, put in Ray's object store once
        pending = {}
        try:
            for job in jobs:
                # Named from anywhere: a worker's current folder is not the driver's.
                job = replace(job, out=os.path.abspath(job.out), scene_xml=os.path.abspath(job.scene_xml),
                              config={**job.config, "scene": os.path.abspath(job.config["scene"])})
                # The scene's files by reference: Ray hands a task the objects of its own arguments.
                scene, planner, run = _inputs(job, bundles, ray)
                pending[task.remote(run_job, job, threads, options.storage, _folder_id(Path(job.out).parents[2]),
                                    scene, planner, run)] = job
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                job = pending.pop(done[0])
                try:
                    status = ray.get(done[0])
                except exceptions.RayTaskError as exc:
                    cause = getattr(exc, "cause", None)
                    raise (cause if isinstance(cause, Exception) else UserError(
                        f"run {job.scene}/{job.planner}/{job.seed} failed: {str(exc).splitlines()[0]}")) from None
                except (exceptions.WorkerCrashedError, exceptions.NodeDiedError, exceptions.OutOfMemoryError):
                    raise UserError(f"run {job.scene}/{job.planner}/{job.seed}: its worker died in each of its "
                                    f"{options.retries + 1} tries (--retries {options.retries}); its run "
                                    "folder keeps what it had") from None
                if "files" in status:
                    _put_back(Path(job.out), status.pop("files"))
                bar.set_postfix_str(status["job"])
                bar.update()
        except BaseException:  # Ctrl-C, or a failed run: the others stop through their clean-up
            for ref in pending:
                ray.cancel(ref)
            raise


def _folder_id(folder: Path) -> tuple | None:
    """What tells a worker that it sees the driver's suite folder: its path and inode
    (a device number is each NFS client's own)."""
    with contextlib.suppress(OSError):
        return str(folder.absolute()), folder.stat().st_ino
    return None


def _sees(folder_id) -> bool:
    if folder_id is None:
        return False
    path, ino = folder_id
    with contextlib.suppress(OSError):
        return Path(path).stat().st_ino == ino
    return False


def _read_tree(root: Path, paths) -> dict:
    """``{path relative to root: bytes}`` of the files ``paths``."""
    return {str(p.relative_to(root)): p.read_bytes() for p in paths}


def _write_tree(root: Path, files: dict) -> None:
    for rel, data in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def _inputs(job, bundles: dict, ray) -> tuple:
    """What a worker without the suite folder needs to run ``job``: the scene's
    files (its XML and the files it names, or a dataset's ``job.scene_files``, below
    their common folder), a planner file of the user's own, and the files the run folder holds."""
    xml = Path(job.scene_xml)
    if job.scene_xml not in bundles:
        files = ([Path(f) for f in job.scene_files] if job.scene_files is not None
                 else [xml.resolve(), *(p.resolve() for p in referenced_files(xml))])
        root = Path(os.path.commonpath([p.parent for p in files]))
        bundles[job.scene_xml] = ray.put({"xml": str(xml.resolve().relative_to(root)),
                                          "files": _read_tree(root, files)})
    planner = None
    if is_planner_file(job.config["planner"]):
        where, _, cls = job.config["planner"].rpartition(":")
        planner = {"name": Path(where).name, "class": cls, "code": Path(where).read_bytes()}
    out = Path(job.out)
    run = _read_tree(out, [p for p in out.rglob("*") if p.is_file()]) if out.is_dir() else {}
    return bundles[job.scene_xml], planner, run


def _ray_task(run_job, job, threads: int, storage: str, folder_id, scene: dict, planner: dict | None,
              run: dict) -> dict:
    """One run (``run_job``, as :func:`run_local` takes it), in a Ray worker: in the suite
    folder when this worker sees it, else in a scratch folder whose run folder goes back to the driver."""
    _show_warnings_as_lines()
    if storage == "auto" and _sees(folder_id):
        return run_job(job, threads)
    with tempfile.TemporaryDirectory(prefix="mitsuba-active-run-") as scratch:
        scratch = Path(scratch)
        _write_tree(scratch / "scene", scene["files"])
        config = {**job.config, "scene": str(scratch / "scene" / scene["xml"])}
        if planner is not None:
            code = scratch / "planner" / planner["name"]
            _write_tree(code.parent, {code.name: planner["code"]})
            config["planner"] = f"{code}:{planner['class']}"
        out = scratch / "runs" / "scene" / Path(job.out).name
        _write_tree(out, run)
        status = run_job(replace(job, scene_xml=config["scene"], config=config, out=str(out)), threads)
        if not status["skipped"]:
            status["files"] = _read_tree(out, [p for p in out.rglob("*") if p.is_file()])
        return status


def _put_back(out: Path, files: dict) -> None:
    """A run folder sent back by a worker takes the place of ``out`` whole."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with replaced_folder(out) as folder:
        _write_tree(folder, files)

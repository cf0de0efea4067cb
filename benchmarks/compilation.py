"""Compile once per machine: JAX's persistent compilation cache, set up in one place.

Every process that compiles (the command line, the pool's workers, the processes a Dask
cluster's workers drive, the perf benchmarks, the tests) calls :func:`enable` before its
first compilation. The cache lives in a per-user folder by default,
``$XDG_CACHE_HOME/driftbench/jax`` (``~/.cache/driftbench/jax`` where ``XDG_CACHE_HOME`` is
unset); the variable :data:`ENV` or the command line's ``--compile-cache`` names another
folder, or ``off`` to compile everything afresh.

What keys an entry
------------------
JAX keys each executable by the hash of the lowered program, the jaxlib and XLA backend
versions, the compile options, the devices and every flag in ``XLA_FLAGS`` (so the
one-kernel flag of :mod:`integrators.loop` and the workers' thread flag cannot reuse an
executable built without them). On top of that the entries of each pair of jax and jaxlib
versions go to a folder of their own (:func:`folder`), so an upgrade starts afresh and
leaves the old folder to :func:`clear`. Executables that call back into Python (the SuperLU
path) are never written by JAX: their set-up compiles every time.

Programs kept whole
-------------------
JAX needs a program traced and lowered to compute its key, which is most of a warm
set-up. The main programs of a run (the time loop, the start, the recorder's measures,
the case's checks: everything :func:`linalg.compiled.compile_lifted` compiles) are also
kept whole, serialized executables, in the folder's ``programs/`` (:func:`programs`; bound
:data:`linalg.compiled.KEPT_MAX_BYTES`), in two ways (:mod:`linalg.compiled`):

- by content, in every process that enables the cache: named by the hash of the traced
  program, the versions of jax and jaxlib, the processor's features and ``XLA_FLAGS``, and
  loaded without lowering by any process that traces the same program (a test, a suite
  after a change elsewhere in the code);
- by name, for a run: named by :func:`identity`, the hash of this project's code (every
  file of :data:`CODE_PACKAGES`), the versions of :data:`LIBRARIES`, the processor's
  features, ``XLA_FLAGS``, the run's resolved problem, method, settings and device, and
  then per program its call site, function, argument shapes and order, and loaded without
  tracing. Only runs of the project's own problems and methods on the CPU keep programs
  by name (:func:`kept_for`): a plug-in's code is not in the hash.

Bound and clearing
------------------
The folder is kept under :data:`MAX_BYTES`: JAX evicts the least recently used entries,
under a file lock that the processes sharing it take. JAX's cache would count the folder
(every entry's size and last use) at every write, which costs more than compiling a small
program once it holds thousands; :class:`CountedCache` counts it at a process's first
write and again only when that process's writes would pass the bound.
``python -m benchmarks.compilation`` prints where it is and how large; ``--clear`` empties
it.

Honest timing
-------------
A run's set-up time is measured as before, cache or not; :class:`Watch` counts the
compilations of a set-up and where they came from, and the run records it
(``setup_cache``: ``warm`` when every compilation was read from the cache, ``cold`` when
none was, ``partial``, ``memory`` when nothing needed compiling because this process had
compiled it already, ``off`` without a cache).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import platform
import shutil
import stat
import sys
import threading
from pathlib import Path

import jax
import jaxlib
from jax._src import lru_cache

from benchmarks.records import versions
from linalg.compiled import EVICT_TO, KEPT_EVENT, KEPT_MAX_BYTES, keep_by_content, keeping

#: Environment variable naming the cache folder, or ``off``.
ENV = "DRIFTBENCH_COMPILE_CACHE"
#: Most bytes the cache folder holds before the least recently used entries go.
MAX_BYTES = 2 * 1024**3
#: Compilations quicker than this are not written. Zero: the small helpers (a start, a
#: projection, a measure) each take far longer to compile than to read back, and a
#: set-up that compiles even one of them is no longer served by the cache alone.
MIN_COMPILE_S = 0.0

_lock = threading.Lock()
#: Executables read from the cache, and backend compilations (each one, read or compiled).
_counts = {"/jax/compilation_cache/cache_hits": 0, "/jax/core/compile/backend_compile_duration": 0,
           KEPT_EVENT: 0}
#: The packages whose files make up the code hash of :func:`identity`.
CODE_PACKAGES = ("integrators", "problems", "linalg", "studies")
#: The libraries whose versions :func:`identity` includes.
LIBRARIES = ("jax", "jaxlib", "numpy", "scipy", "diffrax", "equinox", "lineax", "optimistix",
             "asdex", "scikit-sundae")
_enabled: list[Path | None] = []


def root(setting: str | None = None) -> Path | None:
    """The cache's base folder: ``setting``, else :data:`ENV`, else the per-user default;
    ``None`` for ``off``."""
    value = setting if setting is not None else os.environ.get(ENV, "")
    if value.strip().lower() == "off":
        return None
    if value.strip():
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "driftbench" / "jax"


def folder(base: Path) -> Path:
    """The folder for this process's jax and jaxlib versions under ``base``."""
    return base / f"jax-{jax.__version__}-jaxlib-{jaxlib.__version__}"


class CountedCache(lru_cache.LRUCache):
    """JAX's persistent cache of executables, bounded by least recent use, with the folder
    counted at this process's first write and again only when what it has written since
    would pass the bound. The least recently used entries then go, as in JAX's cache, but
    down to :data:`linalg.compiled.EVICT_TO` of the bound, as the kept programs' folder
    is, so that the writes after them need no count.

    Between counts the other processes' writes are not seen, so the folder may pass the
    bound by what they wrote until one of them counts again.
    """

    counted: int | None = None

    def _evict_if_needed(self, *, additional_size: int = 0) -> None:
        if self.counted is None or self.counted + additional_size > self.max_size:
            self.counted = _entry_bytes(self.path)
            if self.counted + additional_size > self.max_size:
                room = int(self.max_size * (1 - EVICT_TO))
                super()._evict_if_needed(additional_size=additional_size + room)
                self.counted = _entry_bytes(self.path)
        self.counted += additional_size


def _entry_bytes(where) -> int:
    """The bytes of the executables in JAX's cache folder ``where``."""
    total = 0
    for entry in os.scandir(where):
        if entry.name.endswith(lru_cache._CACHE_SUFFIX):
            with contextlib.suppress(OSError):
                total += entry.stat().st_size
    return total


def _listen(event: str, *args, **kwargs) -> None:
    if event in _counts:
        with _lock:
            _counts[event] += 1


def enable(setting: str | None = None) -> Path | None:
    """Use the persistent cache in this process and in the processes it starts.

    ``setting`` is a folder or ``off`` (default: :data:`ENV`, else the per-user folder). It
    is written to :data:`ENV`, so that child processes (pool workers) use the same folder.
    Call it before the first compilation; a later call with the same setting does nothing.
    Returns the folder in use, or ``None`` when off.
    """
    base = root(setting)
    where = None if base is None else folder(base)
    if _enabled and _enabled[0] == where:
        return where
    os.environ[ENV] = "off" if base is None else str(base)
    if not _enabled:
        jax.monitoring.register_event_listener(_listen)
        jax.monitoring.register_event_duration_secs_listener(_listen)
    if where is not None:
        where.mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
        jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    jax.config.update("jax_enable_compilation_cache", where is not None)
    jax.config.update("jax_compilation_cache_dir", None if where is None else str(where))
    # JAX decides once per process whether it uses a cache, at the first compilation: a
    # process that compiled before this call must be told to decide again.
    from jax._src import compilation_cache
    # The cache JAX builds at that compilation is a CountedCache; a JAX whose module no
    # longer names LRUCache there keeps its own.
    if getattr(compilation_cache, "LRUCache", None) is lru_cache.LRUCache:
        compilation_cache.LRUCache = CountedCache
    compilation_cache.reset_cache()
    _enabled[:] = [where]
    keep_by_content(programs(), json.dumps([versions(("jax", "jaxlib")), platform.machine(),
                                            _cpu_features()]))
    return where


def active() -> Path | None:
    """The folder this process's compilations go to (``None``: off or not enabled)."""
    return _enabled[0] if _enabled else None


def programs() -> Path | None:
    """The folder of programs kept whole (``None``: the cache is off or not enabled)."""
    where = active()
    return None if where is None else where / "programs"


@functools.lru_cache(maxsize=1)
def _code_and_libraries() -> str:
    digest = hashlib.sha256()
    base = Path(__file__).resolve().parent.parent
    for package in CODE_PACKAGES:
        for path in sorted((base / package).rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                digest.update(str(path.relative_to(base)).encode())
                digest.update(path.read_bytes())
    return json.dumps([digest.hexdigest(), versions(LIBRARIES), sys.version, platform.machine(),
                       _cpu_features()])


def _cpu_features() -> str:
    # XLA:CPU compiles for the features of the processor it runs on; a cache folder shared by
    # machines of other processors (a network home) must not hand one's programs to another.
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith("flags")), "")
    except OSError:
        flags = ""
    return hashlib.sha256((platform.processor() + flags).encode()).hexdigest()[:16]


def kept(*parts):
    """The scope (:func:`linalg.compiled.keeping`) in which programs are kept whole and
    loaded under :func:`identity` of ``parts``, which with this project's code must
    determine every program compiled in it; nothing is kept with the cache off."""
    where = programs()
    return keeping(where, identity(*parts) if where is not None else "")


def kept_for(problem, integrator=None, *settings, platform: str = "cpu"):
    """:func:`kept` for building the case of ``problem`` (a resolved
    :class:`~problems.spec.ProblemSpec`), or for a run of it with ``integrator`` and
    ``settings``: nothing is kept where a plug-in defines either (the code hash does not
    cover it) or the run is not on the CPU (loading a GPU program was never tried here)."""
    import integrators
    import problems

    own = (problems.REGISTRY[problem.name].__module__.startswith("problems.")
           and (integrator is None
                or integrators.REGISTRY[integrator.name][0].startswith("integrators.")))
    if not own or platform != "cpu":
        return keeping(None, "")
    return kept(problem.name, problem.arguments,
                None if integrator is None else [integrator.name, integrator.arguments],
                *settings)


def identity(*parts) -> str:
    """The name of what a scope of :func:`linalg.compiled.keeping` compiles: this code's
    hash, the library versions, the processor's features, ``XLA_FLAGS`` (read now: it is
    fixed once JAX has started) and ``parts`` (JSON; the run's resolved problem, method and
    settings)."""
    text = json.dumps([_code_and_libraries(), os.environ.get("XLA_FLAGS", ""), parts],
                      default=repr, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


class Watch:
    """Counts the compilations inside a ``with`` block and where they came from.

    Attributes, after the block: ``compiled`` (backend compilations, the cached ones
    excluded), ``kept`` (programs loaded whole, :mod:`linalg.compiled`), ``hits``
    (executables read from JAX's cache, and ``kept``) and :attr:`source`.
    """

    def __enter__(self) -> "Watch":
        with _lock:
            self._start = tuple(_counts.values())
        return self

    def __exit__(self, *exc) -> None:
        with _lock:
            read, backend, kept = (now - then for now, then in zip(_counts.values(), self._start))
        self.compiled = backend - read
        self.kept = kept
        self.hits = read + kept

    @property
    def source(self) -> str:
        """``off``, ``memory``, ``warm``, ``cold`` or ``partial`` (module docstring)."""
        if active() is None:
            return "off"
        if self.hits == 0 and self.compiled == 0:
            return "memory"
        if self.compiled == 0:
            return "warm"
        return "cold" if self.hits == 0 else "partial"


def _files(where: Path):
    """``(path, stat)`` of each file under a cache folder, as the walk finds it."""
    for path in where.rglob("*"):
        if path.name.startswith("."):
            continue
        try:
            info = path.stat()
        except OSError:  # removed meanwhile: another process keeping the folder in bound
            continue
        if stat.S_ISREG(info.st_mode):
            yield path, info


def _entry(path: Path) -> bool:
    """Whether a file is an entry: one of JAX's executables or a kept program."""
    return path.name.endswith((lru_cache._CACHE_SUFFIX, ".program"))


def size(where: Path) -> tuple[int, int]:
    """Number of entries (JAX's executables and kept programs) and bytes in a cache folder."""
    entries = nbytes = 0
    for path, info in _files(where):
        entries += _entry(path)
        nbytes += info.st_size
    return entries, nbytes


def cold(where: Path | None) -> bool:
    """Whether the cache folder ``where`` (this version's, :func:`folder`) holds nothing
    to read back: missing, empty, or only other versions' entries beside it. ``False``
    with the cache off (``None``): nothing is to be read back either way, and the run says
    so in its ``setup_cache`` column. The walk stops at the first entry: every command
    asks, and a warm folder holds thousands."""
    return where is not None and not any(_entry(path) for path, _ in _files(where))


def first_run_note(where: Path) -> str:
    """What a run on a cold cache ``where`` (:func:`cold`) prints before its runs start;
    it names the folder a user chooses (``where``'s parent)."""
    return (f"note: the compilation cache {where.parent} has nothing for jax {jax.__version__} "
            f"yet: this first run compiles each method's programs, which takes minutes "
            f"(on a suite, most of its time); later runs read them back from the cache. "
            f"--compile-cache DIR or ${ENV} puts the cache elsewhere.")


def clear(base: Path) -> None:
    """Remove the cache folder ``base`` with every version's entries."""
    shutil.rmtree(base, ignore_errors=True)


def main(argv=None) -> int:
    from benchmarks.records import CommandParser

    parser = CommandParser(prog="python -m benchmarks.compilation",
                           description="Where the persistent compilation cache is, its size; "
                                       "--clear empties it.")
    parser.add_argument("--compile-cache", metavar="DIR", default=None,
                        help=f"the cache folder (default: ${ENV}, else the per-user folder)")
    parser.add_argument("--clear", action="store_true", help="remove every entry")
    args = parser.parse_args(argv)
    base = root(args.compile_cache)
    if base is None:
        print("the compilation cache is off")
        return 0
    if args.clear:
        clear(base)
        print(f"cleared {base}")
        return 0
    entries, nbytes = size(base) if base.exists() else (0, 0)
    print(f"{base}: {entries} entries, {nbytes / 1e6:.1f} MB (bounds per jax version: "
          f"{MAX_BYTES / 1e9:.1f} GB of JAX's executables, {KEPT_MAX_BYTES / 1e9:.1f} GB of "
          f"kept programs); this version's folder: {folder(base).name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Compiling with the large constant arrays as arguments of the program, not inside it.

The structured linear algebra closes over index arrays (a banded assembly's gathers, a
block mass's seeds and group indices, a pattern's rows and columns), so JAX captures
them as constants of every program that calls it, and XLA embeds each in the executable
and copies it while it compiles. A constant is captured once per array, but an array
that JAX derives from one while tracing (``jnp.take`` converts its index to ``int64``) is
a new array at every call site: RATTLE's loop on ``rigid-chain:N=16384`` held 271
constants, 390 MB, most of them copies of a few arrays, and compiling it took the
process from 2.1 to 3.5 GB.

:func:`compile_lifted` traces the function, passes every constant of at least
:data:`LIFT_BYTES` to the executable as an argument instead (one buffer per distinct
value, kept with the executable), and compiles. Smaller constants stay in the program,
where XLA may fold them, so small systems compile as before. What the compiler freed is
then given back to the system (:func:`give_back_heap`).

Programs kept on disk
---------------------
JAX's persistent cache (:mod:`benchmarks.compilation`) spares XLA's compilation but not
tracing and lowering, which it needs for its key: most of a warm set-up of a small
problem is then Python. :func:`compile_lifted` keeps what it compiles as files in two
ways, each holding the serialized executable and the structure of its arguments and
results.

*By content* (:func:`keep_by_content`, in every process that uses the cache): a program
is named by the hash of what it was traced to: its jaxpr as printed (every equation with
its parameters and literals), the values of the constants it holds, the types of those it
takes as arguments and of its inputs, the donated inputs, JAX's settings, ``XLA_FLAGS``,
the device and the library versions. Whatever code or scope traced it, the same hash is
the same program, so a later process that traces it again loads it without lowering, and
so do tests and suites of other code that trace to it. Programs of a primitive JAX did not
know when keeping began (a plug-in's own primitive, whose lowering the hash does not
cover) are not kept this way.

*By name* (inside :func:`keeping`, a folder and an identity): a later process in the same
scope loads the program without tracing it either. The identity must determine every
program compiled in the scope: the caller gives the run's resolved problem and method,
settings, device, the code's hash and the library versions
(:func:`benchmarks.execute.execute`), and each program is then named by its call site,
function, argument shapes, the caller's ``name`` for it and the order of such calls in
the scope. The order alone cannot tell apart two programs of one call site: a call that an
in-memory cache spares in one process and not in another shifts it, so a site that
compiles more than one program names each.

Programs that call back into Python (``pure_callback``: the SuperLU path) are kept in
neither way, and no program whose lifted constants exceed :data:`KEEP_BYTES` is kept by
name. A file that cannot be read back is compiled afresh and overwritten; the folder is
kept under :data:`KEPT_MAX_BYTES` by dropping the least recently used files.
"""

from __future__ import annotations

import contextlib
import contextvars
import ctypes
import hashlib
import io
import os
import pickle
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, Iterator

import jax
import numpy as np

#: Constants of at least this many bytes become arguments.
LIFT_BYTES = 1 << 14
#: Programs whose lifted constants exceed this many bytes are not kept on disk: a large
#: system's index arrays cost more to store and read than to derive.
KEEP_BYTES = 64 << 20
#: Most bytes the folder of kept programs holds before the least recently used go.
KEPT_MAX_BYTES = 1 << 30
#: The share of its bound a folder of compiled programs is brought down to when a write
#: would pass the bound: the writes after it then need no count (a folder kept at its
#: bound would be counted at every write).
EVICT_TO = 0.9
#: Event recorded (``jax.monitoring``) for each program loaded from the folder.
KEPT_EVENT = "/driftbench/compiled/kept_program_loaded"


def _malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc: nothing to give back this way
        return None


_TRIM = _malloc_trim()


def give_back_heap() -> None:
    """Return the C heap's free pages to the system (glibc's ``malloc_trim``; elsewhere
    nothing).

    Set-up frees a lot at once: the compiler's working memory, a pattern tracing's Python
    sets (:func:`linalg.pattern.traced_sparsity`). glibc keeps such pages in the process,
    resident, under everything it does next: after building rigid-chain:N=8192 the
    process was 816 MB resident, 608 MB once they were given back.
    """
    if _TRIM is not None:
        _TRIM(0)


def device_index(a) -> jax.Array:
    """An index array on the device, as ``int32``, made once: a concrete array even when
    first asked for inside a trace (it is cached and used by later traces, so a tracer
    there would leak into them), and one constant for every program that reads it (a copy
    per call would be a constant per call site). Put on the device as it is: ``jnp.asarray``
    would compile a copying program for each new shape."""
    with jax.ensure_compile_time_eval():
        return jax.device_put(np.asarray(a, dtype=np.int32))


class Lifted:
    """A compiled function whose large constants are passed in as arguments.

    Called with the same (non-static) arguments as the function it was compiled from;
    :meth:`as_text` is the executable's.
    """

    def __init__(self, compiled, values: list[jax.Array], out_tree):
        self._compiled, self._values, self._out_tree = compiled, values, out_tree

    def __call__(self, *args):
        out = self._compiled(self._values, *jax.tree_util.tree_leaves(args))
        return jax.tree_util.tree_unflatten(self._out_tree, out)

    def as_text(self) -> str:
        return self._compiled.as_text()

    @property
    def lifted_bytes(self) -> int:
        """Bytes of the constants held as arguments."""
        return sum(v.nbytes for v in self._values)

    @property
    def buffer_bytes(self) -> int | None:
        """Bytes of the buffers XLA assigned to the program (arguments, results and
        temporaries, the lifted constants included), where it reports them. They are fixed
        when the program is compiled, whatever its arguments' values (such as a time loop's
        step count)."""
        try:
            stats = self._compiled.memory_analysis()
        except Exception:   # not every executable (a deserialized one) reports it
            return None
        if stats is None:
            return None
        return int(stats.argument_size_in_bytes + stats.output_size_in_bytes
                   + stats.temp_size_in_bytes - stats.alias_size_in_bytes)

    @property
    def flops(self) -> float | None:
        """XLA's count of the program's floating-point operations, where it gives one.

        Each loop body counts once (XLA does not know how often a while loop runs): for a
        time loop, about one step with one Newton iteration and its recording.
        """
        cost = self._compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, list) and cost else cost
        return float(cost["flops"]) if isinstance(cost, dict) and "flops" in cost else None


class _Keeper:
    """The folder and identity of a :func:`keeping` scope, and the calls made in it."""

    def __init__(self, folder: Path, identity: str):
        self.folder, self.identity = folder, identity
        self.calls: dict[str, int] = {}

    def path(self, fn: Callable, args: tuple, static: dict, name: str) -> Path:
        """The file of the program that :func:`compile_lifted` (this method's caller) is
        asked for: named by the scope's identity, the call site, the function, the shapes,
        plain static arguments and ``name``, and how many such calls the scope made
        before."""
        caller = sys._getframe(2)  # compile_lifted's caller
        site = f"{Path(caller.f_code.co_filename).name}:{caller.f_lineno}"
        inner = getattr(fn, "func", fn)
        qualified = f"{getattr(inner, '__module__', '')}.{getattr(inner, '__qualname__', inner)}"
        leaves, tree = jax.tree_util.tree_flatten(args)
        shapes = [(np.shape(x), str(getattr(x, "dtype", type(x))),
                   bool(getattr(x, "weak_type", False))) for x in leaves]
        plain = sorted((k, repr(v)) for k, v in static.items()
                       if isinstance(v, (str, int, float, bool, type(None))))
        call = repr((site, qualified, name, str(tree), shapes, plain))
        order = self.calls.get(call, 0)
        self.calls[call] = order + 1
        digest = hashlib.sha256(f"{self.identity}\n{call}\n{order}".encode()).hexdigest()
        return self.folder / f"{digest[:40]}.program"

    def load(self, path: Path) -> "Lifted | None":
        kept = _fetch(path)
        if kept is None or len(kept[2]) != 2:
            return None
        _, compiled, (values, result_tree) = kept
        return Lifted(compiled, [jax.device_put(v) for v in values], result_tree)

    def save(self, path: Path, executable: tuple, values: list[jax.Array], result_tree) -> None:
        """Write the program: ``executable`` as :func:`_serialized` gives it."""
        if sum(v.nbytes for v in values) <= KEEP_BYTES:
            _store(path, (*executable, [np.asarray(v) for v in values], result_tree))


def _fetch(path: Path) -> tuple | None:
    """What ``path`` keeps: ``(executable, compiled, rest)``, the serialized executable
    (:func:`_serialized`), the program loaded from it (and counted, :data:`KEPT_EVENT`) and
    the rest of the record; ``None`` where it is missing or cannot be read or loaded."""
    from jax.experimental import serialize_executable
    if not _lapack_ready():
        return None
    try:
        with open(path, "rb") as f:
            payload, in_tree, out_tree, *rest = pickle.load(f)
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
        os.utime(path)  # recently used: the last to be dropped
    except Exception:  # missing, damaged or foreign: compiled afresh and written anew
        return None
    jax.monitoring.record_event(KEPT_EVENT)
    return (payload, in_tree, out_tree), compiled, rest


def _store(path: Path, record: tuple) -> None:
    """Write ``record`` to ``path`` whole, then rename it: a process reading it never sees
    part of a file. A full or read-only disk, or a record pickle cannot write, only leaves
    it not kept."""
    try:
        data = pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, temporary = tempfile.mkstemp(dir=path.parent, suffix=".part")
    except Exception:
        return
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(temporary, path)
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        return
    # The folder is counted (every file's size) at this process's first write and again
    # only when what it has written since would pass the bound: a count per write costs
    # more than the write once the folder holds thousands of programs.
    counted = _counted.get(path.parent)
    if counted is None or counted + len(data) > KEPT_MAX_BYTES:
        _counted[path.parent] = _bound(path.parent, KEPT_MAX_BYTES, EVICT_TO)
    else:
        _counted[path.parent] = counted + len(data)


def _serialized(compiled, read: bytes | None) -> tuple | None:
    """``(payload, in_tree, out_tree)`` of a compiled program, as :func:`_fetch` reads it;
    ``read``: its executable as JAX's persistent cache read or wrote it (``None``: not
    there), see :func:`_remember_cache_bytes`. ``None`` where it cannot be serialized."""
    from jax.experimental import serialize_executable
    try:
        if read is None:
            return serialize_executable.serialize(compiled)
        return _serialize_as_read(compiled, read)
    except Exception:  # a pytree node pickle does not know: not kept
        return None


#: The serialized executable that JAX's persistent cache last read or wrote in this thread.
_read = threading.local()


def _remember_cache_bytes() -> None:
    """Have JAX's persistent cache leave the bytes of each executable it reads or writes
    in :data:`_read`.

    An XLA:CPU executable loaded from serialized bytes cannot be serialized again (the
    copy lacks its kernels: "Function ... not found" when called), so a program that JAX's
    cache served is kept from the bytes that cache read; and one it compiled, from the
    bytes the cache wrote, which spares serializing it a second time. JAX has no hook for
    this; its functions that split a cache entry into executable and compile time and join
    them are wrapped (once; where the first is missing, such programs are only not kept,
    and where the second is, serialized again).
    """
    from jax._src import compilation_cache
    for name in ("extract_executable_and_time", "combine_executable_and_time"):
        original = getattr(compilation_cache, name, None)
        if original is not None and not getattr(original, "remembers", False):
            setattr(compilation_cache, name, _remembering(original, name.startswith("extract")))


def _remembering(original: Callable, splits: bool) -> Callable:
    def remembering(*args):
        result = original(*args)
        _read.serialized = result[0] if splits else args[0]
        return result

    remembering.remembers = True
    return remembering


def _serialize_as_read(compiled, serialized: bytes):
    """:func:`jax.experimental.serialize_executable.serialize` with the executable's bytes
    as JAX's cache read or wrote them."""
    from jax.experimental import serialize_executable

    class Pickler(serialize_executable._JaxPjrtPickler):
        def persistent_id(self, obj):
            if obj is executable:
                return ("exec", serialized)
            return super().persistent_id(obj)

    unloaded = compiled._executable._unloaded_executable
    executable = unloaded.xla_executable
    flat, in_tree = jax.tree_util.tree_flatten(compiled.args_info)
    with io.BytesIO() as f:
        Pickler(f).dump((unloaded, flat, compiled._no_kwargs))
        return f.getvalue(), in_tree, compiled.out_tree


def _lapack_ready() -> bool:
    """Bind jaxlib's LAPACK kernels, as lowering a LAPACK call would.

    A program loaded without being lowered in this process calls LAPACK through pointers
    that only this binding sets: without it the first solve crashes the process. JAX's
    own loader of serialized programs does the same; where the function is missing, no
    program is loaded.
    """
    try:
        from jax._src.lax.linalg import initialize_lapack
        initialize_lapack()
    except (ImportError, AttributeError):
        return False
    return True


#: Bytes of each folder of kept programs when this process last counted them
#: (:func:`_bound`), with what it has written there since.
_counted: dict[Path, int] = {}


def _bound(folder: Path, limit: int, keep: float = 1.0) -> int:
    """Where the programs of ``folder`` take more than ``limit`` bytes, drop the least
    recently used until they take at most ``keep * limit``; the bytes they then take."""
    entries = []
    for entry in os.scandir(folder):
        if not entry.name.endswith(".program"):
            continue
        with contextlib.suppress(OSError):
            info = entry.stat()
            entries.append((info.st_mtime, info.st_size, entry.path))
    total = sum(size for _, size, _ in entries)
    if total <= limit:
        return total
    for _, size, path in sorted(entries):
        if total <= keep * limit:
            break
        with contextlib.suppress(OSError):
            os.unlink(path)
            total -= size
    return total


_keeper: contextvars.ContextVar[_Keeper | None] = contextvars.ContextVar("keeper", default=None)


@contextlib.contextmanager
def keeping(folder: Path | None, identity: str):
    """Keep the programs :func:`compile_lifted` compiles inside the block in ``folder``, and
    load those kept by an earlier block with the same ``identity`` (module notes).

    ``identity`` must determine every program compiled in the block; ``folder`` ``None``
    keeps nothing.
    """
    if folder is not None:
        _remember_cache_bytes()
    token = _keeper.set(None if folder is None else _Keeper(Path(folder), identity))
    try:
        yield
    finally:
        _keeper.reset(token)


#: The folder of programs kept by their content (:func:`keep_by_content`), what besides
#: the program determines its executable, and the primitives JAX had lowering rules for.
_by_content: list = [None, "", frozenset()]


def _jax_primitives() -> frozenset:
    from jax._src.interpreters import mlir
    rules = [mlir._lowerings, *getattr(mlir, "_platform_specific_lowerings", {}).values()]
    return frozenset(p for table in rules for p in table)


def keep_by_content(folder: Path | None, salt: str = "") -> None:
    """Keep every program :func:`compile_lifted` compiles in ``folder`` (``None``: none),
    named by the hash of its traced content (module notes); ``salt`` names what else
    decides the executable (the library versions, the processor).

    Only programs of primitives that JAX could lower when this was called are kept: one
    registered later (a plug-in's own primitive) has a lowering the hash does not cover.
    """
    if folder is not None:
        _remember_cache_bytes()
    _by_content[:] = [None if folder is None else Path(folder), salt,
                      frozenset() if folder is None else _jax_primitives()]


def _content_path(closed, slots: dict[int, int], values: list[jax.Array],
                  donated: list[bool]) -> Path | None:
    """The file of a traced program kept by its content: the hash of its jaxpr (printed:
    every equation, its parameters and literals), the values of the constants it holds and
    the types of those it takes as arguments, of its inputs, the donated inputs, JAX's
    settings, ``XLA_FLAGS``, the device and the salt. ``None`` outside
    :func:`keep_by_content`, for a primitive it does not know, or for a constant that has no
    bytes (an extended type, an object)."""
    folder, salt, known = _by_content
    if folder is None:
        return None
    inner = []
    for eqn in equations(closed.jaxpr):
        if eqn.primitive not in known:
            return None
        inner += [c for param in eqn.params.values()
                  for sub in (param if isinstance(param, (tuple, list)) else (param,))
                  for c in getattr(sub, "consts", ())]
    digest = hashlib.sha256(salt.encode())
    digest.update(repr(sorted((k, repr(v)) for k, v in jax.config.values.items())).encode())
    digest.update(os.environ.get("XLA_FLAGS", "").encode())
    device = jax.devices()[0]
    digest.update(f"{device.platform} {device.device_kind}".encode())
    digest.update(str(closed.jaxpr).encode())
    digest.update(repr([(a.shape, str(a.dtype), a.weak_type) for a in closed.in_avals]).encode())
    digest.update(repr([(v.shape, str(v.dtype), getattr(v, "weak_type", False))
                        for v in values] + [slots, donated]).encode())
    try:
        for i, c in enumerate(list(closed.consts) + inner):
            if i in slots:  # an argument: its values are not in the program
                continue
            array = np.asarray(c)
            if array.dtype == object:  # its bytes would be addresses
                return None
            digest.update(repr((array.shape, array.dtype.str)).encode())
            digest.update(np.ascontiguousarray(array).tobytes())
    except Exception:
        return None
    return folder / f"content-{digest.hexdigest()[:40]}.program"


def equations(jaxpr) -> Iterator:
    """The equations of a jaxpr and of every jaxpr nested in it (loop bodies, branches,
    inner calls)."""
    for eqn in jaxpr.eqns:
        yield eqn
        for param in eqn.params.values():
            for sub in param if isinstance(param, (tuple, list)) else (param,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    yield from equations(inner)


def _calls_back(jaxpr) -> bool:
    """Whether a jaxpr (or one nested in it) calls back into Python."""
    return any("callback" in eqn.primitive.name for eqn in equations(jaxpr))


def compile_lifted(fn: Callable, *args: Any, donate: tuple[int, ...] = (),
                   name: str = "", **static: Any) -> Lifted:
    """``jax.jit(fn).lower(*args, **static).compile()`` with the constants of at least
    :data:`LIFT_BYTES` passed as arguments (module notes); the program an earlier process
    kept is loaded instead, or this one kept: by name inside :func:`keeping` (before
    tracing), by content under :func:`keep_by_content` (after tracing).

    Parameters
    ----------
    fn : callable
        A function of arrays, or a ``jax.jit`` function (then ``static`` are its static
        arguments, by name).
    *args
        Arrays (or shape-dtype structures) of the call's shapes.
    donate : tuple of int
        Positions in ``args`` whose arrays the program may reuse for its results
        (``jax.jit``'s ``donate_argnums``): a caller that hands them over spares the copy
        of a large buffer it would not read again.
    name : str
        What tells this program from others compiled at the same call site with the same
        shapes, in the name of its kept file. Without it only their order in the scope
        does, and a call that an in-memory cache spares shifts the order of the next.
    """
    keeper = _keeper.get()
    path = keeper.path(fn, args, static, name) if keeper is not None else None
    if path is not None:
        kept = keeper.load(path)
        if kept is not None:
            return kept
    jitted = fn if hasattr(fn, "trace") else jax.jit(fn)
    traced = jitted.trace(*args, **static)
    closed = traced.jaxpr
    consts = list(closed.consts)
    # A trace has one input per argument leaf. More inputs are values it closed over that
    # JAX could not take as constants: a tracer leaked from an earlier trace, such as an
    # index array cached while tracing (hence linalg.compiled.device_index).
    if len(closed.jaxpr.invars) != len(jax.tree_util.tree_leaves(args)):
        raise RuntimeError(f"compile_lifted: the trace of {getattr(fn, '__name__', fn)} "
                           "closes over values that are not constants (a leaked tracer?)")
    values: list[jax.Array] = []
    slots: dict[int, int] = {}
    for i, c in enumerate(consts):
        if np.ndim(c) == 0 or c.nbytes < LIFT_BYTES:
            continue
        same = next((k for k, v in enumerate(values)
                     if v.shape == c.shape and v.dtype == c.dtype
                     and getattr(v, "weak_type", False) == getattr(c, "weak_type", False)
                     and np.array_equal(v, c)), None)
        if same is None:
            values.append(jax.device_put(c))
            same = len(values) - 1
        slots[i] = same
        consts[i] = None  # not kept: the copies go with the trace
    jaxpr = closed.jaxpr

    def run(lifted, *flat):
        bound = [lifted[slots[i]] if i in slots else c for i, c in enumerate(consts)]
        return jax.core.eval_jaxpr(jaxpr, bound, *flat)

    flat_args = jax.tree_util.tree_leaves(args)
    # The flat arguments follow the lifted constants (argument 0 of run).
    given = [i in donate for i, arg in enumerate(args) for _ in jax.tree_util.tree_leaves(arg)]
    calls_back = _calls_back(jaxpr)
    by_content = None if calls_back else _content_path(closed, slots, values, given)
    kept = None if by_content is None else _fetch(by_content)
    record = None
    if kept is not None:
        record, compiled, _ = kept
    else:
        lowered = jax.jit(run, donate_argnums=tuple(1 + i for i, d in enumerate(given) if d)
                          ).lower(values, *flat_args)
        _read.serialized = None
        compiled = lowered.compile()
        give_back_heap()
        if by_content is not None or (path is not None and not calls_back):
            record = _serialized(compiled, _read.serialized)
        if by_content is not None and record is not None:
            _store(by_content, record)
    if path is not None and record is not None:
        keeper.save(path, record, values, traced.out_tree)
    return Lifted(compiled, values, traced.out_tree)

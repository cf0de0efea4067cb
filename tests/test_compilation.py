"""Compile once: programs kept whole (:mod:`linalg.compiled`) and the persistent cache's
bookkeeping (:mod:`benchmarks.compilation`).

The end-to-end tests run the command line in fresh processes on a cache folder of their
own, so that what a later process loads was written by an earlier one.
"""

from __future__ import annotations

import csv
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import compilation
from linalg import compiled
from linalg.compiled import compile_lifted, keeping

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def by_name_only(monkeypatch):
    """The tests of programs kept by name see no program kept by its content."""
    monkeypatch.setattr(compiled, "_by_content", [None, "", frozenset()])


def programs_in(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.program"))


def loaded(fn, *args, folder: Path, identity: str):
    """Compile ``fn`` in a keeping scope; how many programs were loaded from ``folder``."""
    with compilation.Watch() as watch, keeping(folder, identity):
        out = compile_lifted(fn, *args)(*args)
    return out, watch


def test_a_kept_program_is_loaded_by_the_same_identity_and_gives_the_same_values(tmp_path):
    def f(x):
        return jnp.linalg.solve(jnp.eye(3) * 2.0 + x[:, None], x) + jnp.sin(x)

    x = jnp.arange(3.0)
    first, _ = loaded(f, x, folder=tmp_path, identity="run A")
    assert len(programs_in(tmp_path)) == 1
    again, watch = loaded(f, x, folder=tmp_path, identity="run A")
    assert watch.kept == watch.hits == 1 and watch.compiled == 0 and watch.source == "warm"
    np.testing.assert_array_equal(np.asarray(again), np.asarray(first))
    # Another identity is another program.
    loaded(f, x, folder=tmp_path, identity="run B")
    assert len(programs_in(tmp_path)) == 2


def test_two_calls_of_one_site_in_a_scope_are_two_programs(tmp_path):
    def scaled(scale):  # one call site, one function name, the same shapes
        return float(compile_lifted(lambda x: x * scale, jnp.ones(2))(jnp.ones(2))[0])

    with keeping(tmp_path, "same run"):
        assert (scaled(2.0), scaled(3.0)) == (2.0, 3.0)
    assert len(programs_in(tmp_path)) == 2
    with compilation.Watch() as watch, keeping(tmp_path, "same run"):
        assert (scaled(2.0), scaled(3.0)) == (2.0, 3.0)
    assert watch.kept == 2


def test_a_named_program_is_found_by_its_name_when_a_call_before_it_was_spared(tmp_path):
    # The loop without and with the Newton fallback: one call site, the same shapes. An
    # in-memory cache may spare the first call in a later scope; the second must not then
    # load the first's program.
    def scaled(scale, name):
        program = compile_lifted(lambda x: x * scale, jnp.ones(2), name=name)
        return float(program(jnp.ones(2))[0])

    with keeping(tmp_path, "same run"):
        assert (scaled(2.0, "plain"), scaled(3.0, "with fallback")) == (2.0, 3.0)
    with compilation.Watch() as watch, keeping(tmp_path, "same run"):
        assert scaled(3.0, "with fallback") == 3.0
    assert watch.kept == 1


def test_a_program_that_calls_back_into_python_is_not_kept(tmp_path):
    def f(x):
        y = jax.pure_callback(lambda a: np.asarray(a) * 2.0, jax.ShapeDtypeStruct((2,), x.dtype), x)
        return y + 1.0

    out, _ = loaded(f, jnp.ones(2), folder=tmp_path, identity="callback")
    assert np.all(np.asarray(out) == 3.0)
    assert programs_in(tmp_path) == []


def test_a_damaged_program_is_compiled_afresh_and_replaced(tmp_path):
    def f(x):
        return x * 2.0 + 1.0

    loaded(f, jnp.ones(2), folder=tmp_path, identity="damaged")
    (path,) = programs_in(tmp_path)
    path.write_bytes(b"not a program")
    out, watch = loaded(f, jnp.ones(2), folder=tmp_path, identity="damaged")
    assert np.all(np.asarray(out) == 3.0) and watch.kept == 0
    assert path.read_bytes() != b"not a program"
    _, watch = loaded(f, jnp.ones(2), folder=tmp_path, identity="damaged")
    assert watch.kept == 1


def test_the_folder_is_bounded_by_dropping_the_least_recently_used(tmp_path):
    for i, age in enumerate((30, 10, 20)):
        p = tmp_path / f"{i}.program"
        p.write_bytes(b"x" * 100)
        os.utime(p, (time.time() - age, time.time() - age))
    compiled._bound(tmp_path, 200)
    assert sorted(p.name for p in programs_in(tmp_path)) == ["1.program", "2.program"]


def test_writes_keep_the_folder_bounded_though_it_is_counted_only_when_they_pass(
        tmp_path, monkeypatch):
    record = (b"x" * 1000,)
    size = len(pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL))
    monkeypatch.setattr(compiled, "KEPT_MAX_BYTES", 3 * size)
    monkeypatch.setattr(compiled, "_counted", {})
    counts = []
    bound = compiled._bound
    monkeypatch.setattr(compiled, "_bound", lambda *a: counts.append(1) or bound(*a))
    for i in range(7):
        compiled._store(tmp_path / f"{i}.program", record)
        time.sleep(0.01)  # distinct times of use
    # Counted at the first write, then at each that would pass three records, which
    # leaves 90 % of them (two whole records): the 4th and the 6th, not the 5th and 7th.
    assert len(counts) == 3
    assert sum(p.stat().st_size for p in programs_in(tmp_path)) <= 3 * size
    assert (tmp_path / "6.program").exists()  # the newest stays


def test_jax_cache_writes_keep_it_bounded_though_it_is_counted_only_when_they_pass(
        tmp_path, monkeypatch):
    # JAX's own cache counts every entry's size and last use at every write.
    from jax._src import compilation_cache, lru_cache
    full, scans = [], []
    evict, entry_bytes = lru_cache.LRUCache._evict_if_needed, compilation._entry_bytes
    monkeypatch.setattr(lru_cache.LRUCache, "_evict_if_needed",
                        lambda self, **kw: full.append(1) or evict(self, **kw))
    monkeypatch.setattr(compilation, "_entry_bytes", lambda w: scans.append(1) or entry_bytes(w))
    cache = compilation.CountedCache(str(tmp_path), max_size=10_000)
    for i in range(14):
        cache.put(f"k{i}", b"x" * 1000)
        assert sum(p.stat().st_size for p in tmp_path.glob("*-cache")) <= 10_000
        time.sleep(0.01)  # distinct times of use
        if i == 5:
            assert cache.get("k0") is not None  # k0 used after k5 was written
        if i == 10:  # the first write past the bound: down to 9 entries with it
            left = sorted(int(p.name[1:-6]) for p in tmp_path.glob("*-cache"))
            assert left == [0, *range(3, 11)]
    # Counted at the first write (one scan), and twice at each write past the bound (the
    # 11th and the 13th, each then counted in full for the least recently used).
    assert len(scans) == 5 and len(full) == 2
    # The cache of every process that enables it is this one.
    assert compilation_cache.LRUCache is compilation.CountedCache


def test_the_identity_holds_the_code_the_xla_flags_and_the_run(monkeypatch):
    base = compilation.identity("pendulum", 0.01)
    assert compilation.identity("pendulum", 0.01) == base
    assert compilation.identity("pendulum", 0.02) != base
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=false")
    assert compilation.identity("pendulum", 0.01) != base


def test_a_cache_is_cold_without_entries_for_this_version(tmp_path):
    where = compilation.folder(tmp_path)
    assert compilation.cold(where)  # missing
    where.mkdir()
    assert compilation.cold(where)  # empty
    other = tmp_path / "jax-0.0.1-jaxlib-0.0.1"
    other.mkdir()
    (other / "jit_run-0123-cache").write_bytes(b"x")
    assert compilation.cold(where)  # another version's entries only
    (where / "programs").mkdir()
    (where / "programs" / "0123.program").write_bytes(b"x")
    assert not compilation.cold(where)
    assert not compilation.cold(None)  # off
    note = compilation.first_run_note(where)
    assert str(tmp_path) in note and "--compile-cache" in note and compilation.ENV in note


@pytest.mark.slow
def test_bad_input_on_a_cold_cache_gets_its_one_line_alone(tmp_path):
    # The step limit is checked while the runs are validated, after the cache was found
    # cold: the first-run note waits for the runs to start, and none starts.
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--problems", "pendulum", "--integrators",
         "rattle", "--h", "1e-9", "--t-end", "1000", "--jobs", "1", "--no-report",
         "--compile-cache", str(tmp_path / "cache"), "--out", str(tmp_path / "out")],
        cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert len(done.stderr.splitlines()) == 1 and done.stderr.startswith("error: ")


def cli_run(out: Path, cache: Path, *args, stderr: list | None = None) -> dict:
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--problems", "pendulum", "--t-end", "1",
         "--jobs", "1", "--no-report", "--compile-cache", str(cache), "--out", str(out), *args],
        cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    if stderr is not None:
        stderr.append(done.stderr)
    with open(out / "runs.csv", newline="") as f:
        return {row["integrator"]: row for row in csv.DictReader(f)}


@pytest.mark.slow
def test_programs_kept_by_one_invocation_run_in_the_next_identically(tmp_path):
    # LAPACK (lobatto3ab2's Newton solves) from a program that was never lowered in the
    # loading process; the kept file written once from a compilation and once from an
    # executable that JAX's own cache served; and, with the named files gone, every
    # program found again by its content: a traced program hashes alike in every process.
    # The first invocation on the empty cache says once that it compiles; the next not.
    cache = tmp_path / "cache"
    args = ("--integrators", "lobatto3ab2", "rattle", "--h", "0.05")
    said: list[str] = []
    cold = cli_run(tmp_path / "cold", cache, *args, stderr=said)
    kept = compilation.folder(cache) / "programs"
    assert programs_in(kept)
    warm = cli_run(tmp_path / "warm", cache, *args, stderr=said)
    note = compilation.first_run_note(compilation.folder(cache))
    assert said[0].count(note) == 1 and note not in said[1]
    for method in ("lobatto3ab2", "rattle"):
        assert cold[method]["status"] == warm[method]["status"] == "ok"
        assert warm[method]["setup_cache"] == "warm"
        assert warm[method]["q_final"] == cold[method]["q_final"]
        assert warm[method]["max_pos_residual"] == cold[method]["max_pos_residual"]
    for p in programs_in(kept):
        p.unlink()
    from_jax = cli_run(tmp_path / "from-jax", cache, *args)
    assert programs_in(kept)
    again = cli_run(tmp_path / "again", cache, *args)
    for method in ("lobatto3ab2", "rattle"):
        assert from_jax[method]["q_final"] == again[method]["q_final"] == cold[method]["q_final"]
        assert again[method]["setup_cache"] == "warm"
    by_content = set(kept.glob("content-*.program"))
    assert by_content
    for p in set(programs_in(kept)) - by_content:
        p.unlink()
    traced = cli_run(tmp_path / "traced", cache, *args)
    assert set(kept.glob("content-*.program")) == by_content
    assert len(programs_in(kept)) > len(by_content)  # the named ones, written anew
    for method in ("lobatto3ab2", "rattle"):
        assert traced[method]["q_final"] == cold[method]["q_final"]
        assert traced[method]["setup_cache"] == "warm"


@pytest.fixture
def by_content(tmp_path, monkeypatch):
    """Programs kept by their content in a folder of the test's own."""
    monkeypatch.setattr(compiled, "_by_content", [None, "", frozenset()])
    compiled.keep_by_content(tmp_path / "content", "salt")
    return tmp_path / "content"


def traced_twice(fn, *args):
    """Compile ``fn`` twice outside any named scope: the results and the second's watch."""
    first = compile_lifted(fn, *args)(*args)
    with compilation.Watch() as watch:
        again = compile_lifted(fn, *args)(*args)
    return np.asarray(first), np.asarray(again), watch


def test_a_program_traced_again_is_loaded_by_its_content(by_content):
    def f(x):
        return jnp.linalg.solve(jnp.eye(3) * 2.0 + x[:, None], x) + jnp.sin(x)

    first, again, watch = traced_twice(f, jnp.arange(3.0))
    assert watch.kept == 1 and watch.compiled == 0
    np.testing.assert_array_equal(again, first)
    assert len(programs_in(by_content)) == 1


def test_a_damaged_program_kept_by_content_is_compiled_afresh_and_replaced(by_content):
    def f(x):
        return x * 2.0 + 1.0

    compile_lifted(f, jnp.ones(2))
    (path,) = programs_in(by_content)
    path.write_bytes(b"not a program")
    with compilation.Watch() as watch:
        out = compile_lifted(f, jnp.ones(2))(jnp.ones(2))
    assert np.all(np.asarray(out) == 3.0) and watch.kept == 0
    _, again, watch = traced_twice(f, jnp.ones(2))
    assert watch.kept == 1 and np.all(again == 3.0)


def test_a_constant_held_in_the_program_is_part_of_its_content(by_content):
    # Small constants stay in the program, where XLA may fold them: other values, another
    # program.
    x = jnp.ones(2)
    for scale in (np.array([2.0, 3.0]), np.array([2.0, 4.0])):
        assert np.all(np.asarray(compile_lifted(lambda y: y * scale, x)(x)) == scale)
    assert len(programs_in(by_content)) == 2


def test_a_lifted_constant_is_an_argument_and_one_program_serves_other_values(by_content):
    n = compiled.LIFT_BYTES // 8
    x = jnp.ones(n)
    for scale in (np.full(n, 2.0), np.full(n, 5.0)):
        assert np.all(np.asarray(compile_lifted(lambda y: y * scale, x)(x)) == scale)
    assert len(programs_in(by_content)) == 1


def test_other_xla_flags_are_another_program(by_content, monkeypatch):
    def f(x):
        return x * 2.0

    compile_lifted(f, jnp.ones(2))
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=false")
    compile_lifted(f, jnp.ones(2))
    assert len(programs_in(by_content)) == 2


def test_calls_back_and_primitives_registered_later_are_not_kept_by_content(by_content):
    from jax.extend.core import Primitive
    from jax.interpreters import mlir

    def called_back(x):
        return jax.pure_callback(lambda a: np.asarray(a) * 2.0,
                                 jax.ShapeDtypeStruct((2,), x.dtype), x) + 1.0

    doubled = Primitive("driftbench_test_doubled")
    doubled.def_abstract_eval(lambda a: a)
    mlir.register_lowering(doubled, mlir.lower_fun(lambda a: a * 2.0, multiple_results=False))
    for fn in (called_back, doubled.bind):
        assert np.all(np.asarray(compile_lifted(fn, jnp.ones(2))(jnp.ones(2))) >= 2.0)
    assert programs_in(by_content) == []


@pytest.mark.slow
def test_with_the_cache_off_nothing_is_kept(tmp_path):
    rows = cli_run(tmp_path / "off", Path("off"), "--integrators", "rattle", "--h", "0.05")
    assert rows["rattle"]["setup_cache"] == "off"


def test_the_size_skips_entries_removed_while_it_is_counted(tmp_path, monkeypatch):
    # Another process keeping the folder in bound may remove an entry after the listing:
    # b before a second look at it, c before the first. Nothing is raised, and what was
    # gone when looked at is not counted.
    for name, data in (("a", b"xx"), ("b", b"yyy"), ("c", b"z")):
        (tmp_path / f"{name}.program").write_bytes(data)
    stat = Path.stat
    looks = {"b.program": 0, "c.program": 0}

    def vanishing(self, *args, **kwargs):
        if self.name in looks:
            looks[self.name] += 1
            if self.name == "c.program" or looks[self.name] > 1:
                raise FileNotFoundError(self)
        return stat(self, *args, **kwargs)

    monkeypatch.setattr(Path, "stat", vanishing)
    assert compilation.size(tmp_path) == (2, 5)

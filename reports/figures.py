"""The report's figures, drawn with matplotlib's object API and returned as SVG text.

No pyplot: figures are built directly, so the report neither touches the global backend
nor keeps figures alive. Text stays text (``svg.fonttype = none``): the browser's
sans-serif font draws it, it can be searched and copied, and the report builds faster than
with glyphs as paths. Ids are salted deterministically so that the same data give the same
file.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import pickle
import queue
import subprocess
import sys
import textwrap
import threading
import traceback
from concurrent.futures import Future

import numpy as np
from matplotlib import rc_context
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import Formatter, LogFormatter, LogLocator, NullLocator

from benchmarks import gate
from benchmarks.records import Status
from reports.analysis import LABELS, Convergence, History, Standing, fmt, label

#: Widest log axis (decades) that gets minor ticks.
MINOR_DECADES = 3
#: Inches of axis per labelled tick: a label such as "1e-12" along x (y, x).
LABEL_INCHES = (0.25, 0.45)

#: Smallest value drawn on a log axis: zeros and round-off below it are drawn at it.
LOG_FLOOR = 1e-17
#: Largest value drawn on a log axis: a run that blew up leaves window maxima such as
#: 2.6e285 (bricard with baumgarte-rk4 at h = 0.01), whose decade ticks pass the largest
#: float and break the axis; its line ends at this ceiling, well above anything meaningful.
LOG_CEILING = 1e100
RC = {"svg.hashsalt": "driftbench", "svg.fonttype": "none", "font.size": 8,
      "axes.grid": True, "grid.alpha": 0.3, "legend.fontsize": 7, "axes.titlesize": 9}
MARKERS = "os^Dv<>pP*Xh"
#: Height of one row of a figure legend, inches (legend font 7 pt and its spacing).
LEGEND_ROW = 0.2
#: Cell colours of the overview by drift class, from kept to lost (a growth class of
#: :mod:`benchmarks.drift`), and for a run that did not finish.
#: Width in inches of a column of the overview's legend: its longest label, "cost winner
#: (wall time)", at 0.06 inch a character, with its patch.
LEGEND_COLUMN = 1.9
CLASS_COLORS = {"bounded": "#a6d96a", "linear": "#fee08b", "quadratic": "#fdae61",
                "superquadratic": "#f46d43", "exponential": "#d73027",
                "indeterminate": "#d9d9d9", "did not finish": "#878787"}


class Drawing:
    """Draws the report's figures side by side in worker processes.

    ``drawing(fn, *args)`` submits the figure function ``fn`` (one of this module's) and
    returns a :class:`~concurrent.futures.Future` of its SVG text, which the document reads
    when it writes the figure (:func:`reports.document.svg_text`). matplotlib draws in
    Python, one figure at a time per process, and drawing was about three quarters of a
    report's build. A figure function that raises raises where its SVG is read.

    A worker is a fresh interpreter that imports this module and nothing of the caller's
    (:func:`_serve`, started through :mod:`subprocess` as the run pool's workers are,
    :mod:`benchmarks.pool`): ``multiprocessing``'s ``spawn`` and ``forkserver`` run the
    caller's main script again in every worker, which in a script without an ``if
    __name__ == "__main__"`` guard starts the caller's sweep over again, and ``fork`` would
    copy JAX's threads in an unknown state. One thread here feeds each worker, starting it
    at its first figure.

    Parameters
    ----------
    jobs : int, optional
        Processes that draw (default: the usable cores). With one, each figure is drawn in
        this process as it is submitted.
    """

    def __init__(self, jobs: int | None = None):
        usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        self.jobs = max(1, jobs if jobs is not None else usable or 1)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._feeders: list[threading.Thread] = []

    def __call__(self, fn, *args) -> Future:
        done: Future = Future()
        if self.jobs == 1:
            try:
                done.set_result(fn(*args))
            except Exception as exc:  # raised again where the SVG is read, as in a worker
                done.set_exception(exc)
            return done
        if not self._feeders:
            self._feeders = [threading.Thread(target=self._feed, daemon=True)
                             for _ in range(self.jobs)]
            for feeder in self._feeders:
                feeder.start()
        self._queue.put((done, fn, args))
        return done

    def _feed(self) -> None:
        """Hand the queued figures one at a time to a worker of this thread's own, until
        the ``None`` that :meth:`__exit__` queues; a worker that dies fails its figure and
        the next figure starts another."""
        worker = None
        try:
            while (item := self._queue.get()) is not None:
                done, fn, args = item
                if not done.set_running_or_notify_cancel():
                    continue
                try:
                    request = pickle.dumps((fn, args))
                except Exception as exc:  # raised where the SVG is read
                    done.set_exception(exc)
                    continue
                try:
                    worker = worker or _start_worker()
                    worker.stdin.write(request)
                    worker.stdin.flush()
                    ok, value = pickle.load(worker.stdout)
                except Exception as exc:  # the worker died, or its answer is unreadable
                    _stop_worker(worker)
                    code = None if worker is None else worker.returncode
                    worker = None
                    done.set_exception(RuntimeError(
                        f"the drawing process failed (exit code {code}) while drawing "
                        f"{getattr(fn, '__name__', fn)}: {exc!r}"))
                    continue
                (done.set_result if ok else done.set_exception)(value)
        finally:
            _stop_worker(worker)

    def __enter__(self) -> "Drawing":
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is not None:
            # Interrupted or failed: what was not drawn yet is not wanted.
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is not None:
                    item[0].cancel()
        for _ in self._feeders:
            self._queue.put(None)
        for feeder in self._feeders:
            feeder.join()
        self._feeders = []


def _start_worker() -> subprocess.Popen:
    """A drawing worker (:func:`_serve`) with this process's ``sys.path``, in a session of
    its own: a Ctrl-C in the terminal reaches this process alone, which decides what an
    interrupt stops."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    return subprocess.Popen([sys.executable, "-c", "from reports.figures import _serve; _serve()"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            env=env, start_new_session=True)


def _stop_worker(worker: subprocess.Popen | None) -> None:
    """Close a worker's input, on which it ends, and wait for it."""
    if worker is None:
        return
    with contextlib.suppress(OSError):
        worker.stdin.close()
    try:
        worker.wait(timeout=10)
    except subprocess.TimeoutExpired:
        worker.kill()
        worker.wait()
    worker.stdout.close()


def _serve() -> None:
    """A drawing worker's loop: read ``(fn, args)`` pickles from standard input until it
    closes, and answer each with ``(True, svg)`` or ``(False, exception)`` on standard
    output, which nothing else may write to (``print`` goes to standard error)."""
    requests, answers = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr
    while True:
        try:
            fn, args = pickle.load(requests)
        except EOFError:
            return
        try:
            answer = (True, fn(*args))
        except Exception as exc:  # the caller raises it where the SVG is read
            answer = (False, exc)
        try:
            blob = pickle.dumps(answer)
        except Exception:  # an exception that does not pickle travels as its text
            blob = pickle.dumps((False, RuntimeError(
                "".join(traceback.format_exception_only(type(answer[1]), answer[1])).strip())))
        answers.write(blob)
        answers.flush()


def palette(families: dict[str, list[str]]) -> dict[str, tuple]:
    """A fixed colour and marker per integrator, the same in every figure.

    ``families`` maps each family (the integrators' ``family`` trait) to its integrators:
    one hue per family, so a reader sees the families at a glance, and within a family
    one shade (from full to pale) and one marker per integrator.
    """
    from matplotlib import colormaps
    from matplotlib.colors import to_rgb

    hues = colormaps["tab10"]
    colors = {}
    for i, family in enumerate(sorted(families)):
        base = np.array(to_rgb(hues(i % hues.N)))
        keys = sorted(families[family])
        for j, key in enumerate(keys):
            pale = 0.55 * j / max(len(keys) - 1, 1)
            colors[key] = (tuple(base + (1.0 - base) * pale), MARKERS[j % len(MARKERS)])
    return colors


class _Distinct(Formatter):
    """Plain labels for ticks off the decades ("2e-03"), with the fewest significant
    digits (up to 4) that tell them apart (an axis that spans less than a decade gets
    ticks at even steps, 0.0026, 0.0028, ..., which one digit would label alike), and
    only those at least ``gap`` decades from a decade and from the last one labelled, so
    that labels do not run into each other."""

    def __init__(self, gap: float):
        self.gap = gap

    def __call__(self, x, pos=None):
        return self.format_ticks([x])[0]

    def format_ticks(self, values):
        for digits in range(1, 5):
            labels = [f"{x:.{digits - 1}e}" for x in values]
            if len(set(labels)) == len(labels):
                break
        last = -math.inf
        for i, x in enumerate(values):
            at = math.log10(x) if x > 0 else -math.inf
            if min(at - last, at - math.floor(at), math.ceil(at) - at) < self.gap:
                labels[i] = ""
            else:
                last = at
        return labels


def _svg(fig: Figure) -> str:
    # Plain tick labels on log axes ("1e-05", not mathtext): typesetting mathtext labels
    # was most of the report's build time.
    # Minor ticks only on log axes of a few decades, where they help reading a value:
    # making the tick objects of the 8 minor ticks per decade on wide axes was half the
    # report's build time. Labelled decades at most one per LABEL_INCHES of the axis, so
    # that a narrow panel's labels do not run into each other.
    width, height = fig.get_size_inches()
    for ax in fig.axes:
        box = ax.get_position()
        for axis, inches in ((ax.xaxis, box.width * width), (ax.yaxis, box.height * height)):
            if axis.get_scale() == "log":
                room = max(inches / LABEL_INCHES[axis is ax.xaxis], 1.0)
                axis.set_major_locator(LogLocator(10.0, numticks=max(2, int(room)) + 1))
                axis.set_major_formatter(LogFormatter(10.0))
                low, high = sorted(axis.get_view_interval())
                decades = math.log10(high / low) if low > 0 else math.inf
                axis.set_minor_formatter(_Distinct(decades / room))
                if decades > MINOR_DECADES:
                    axis.set_minor_locator(NullLocator())
    buf = io.StringIO()
    # A run that blew up (|g| near 1e300) overflows the log axis' tick arithmetic; the
    # ticks that overflow are dropped, which is all that can be drawn there.
    with rc_context(RC), np.errstate(over="ignore"):
        fig.savefig(buf, format="svg", metadata={"Date": None})
    return buf.getvalue()


def _figure(rows: int, cols: int, width: float, height: float) -> tuple[Figure, np.ndarray]:
    with rc_context(RC):
        fig = Figure(figsize=(width, height))
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False))
    return fig, axes


def _arrange(fig: Figure, rows: int, cols: int, legend: tuple | None = None, ncols: int = 1,
             side: float = 0.0) -> None:
    """Fixed margins in inches, and the figure legend below the axes or at their right.

    A layout engine (constrained or tight) measures every tick label to fit the margins,
    which doubled the report's build time; the labels here have bounded widths (log-axis
    labels such as ``1e-05``), so fixed margins fit them. ``legend`` is ``(handles,
    labels)``: below the axes in ``ncols`` columns (the figure grows by its height), or,
    with ``side`` inches reserved, at the right.
    """
    width, height = fig.get_size_inches()
    left, right, top, bottom, wgap, hgap = 0.8, 0.2 + side, 0.6, 0.5, 0.9, 0.65
    if legend and legend[1] and not side:
        grow = 0.15 + LEGEND_ROW * math.ceil(len(legend[1]) / ncols)
        height += grow
        bottom += grow
        fig.set_size_inches(width, height)
        fig.legend(*legend, loc="lower center", ncols=ncols, bbox_to_anchor=(0.5, 0.0))
    elif legend and legend[1]:
        fig.legend(*legend, loc="upper left",
                   bbox_to_anchor=(1.0 - (side + 0.1) / width, 1.0 - top / height))
    axis_w = (width - left - right - (cols - 1) * wgap) / cols
    axis_h = (height - top - bottom - (rows - 1) * hgap) / rows
    fig.subplots_adjust(left=left / width, right=1.0 - right / width, top=1.0 - top / height,
                        bottom=bottom / height, wspace=wgap / axis_w, hspace=hgap / axis_h)


def _floor(y) -> np.ndarray:
    """``y`` for a log axis: raised to :data:`LOG_FLOOR`, cut at :data:`LOG_CEILING`,
    non-finite values left out (NaN)."""
    y = np.asarray(y, dtype=float)
    return np.where(np.isfinite(y), np.clip(y, LOG_FLOOR, LOG_CEILING), np.nan)


def _empty(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")
    ax.set_xticks([])
    ax.set_yticks([])


def drift(entries: list[dict], colors: dict, title: str) -> str:
    """``|g|`` and ``|H - H0|`` (window maxima) against ``t``, log-log, one line per entry.

    Each entry: ``label``, ``integrator``, ``windows`` (``t``, ``pos``, ``energy``),
    ``failed`` (bool) and ``fail_time``. A failed run's line ends in a cross.
    """
    with rc_context(RC):
        fig, axes = _figure(1, 2, 9.0, 3.4)
        panels = (("pos", "max |g| per window"), ("energy", "max |H - H0| per window"))
        for ax, (key, label) in zip(axes[0], panels):
            drawn = 0
            for e in entries:
                w = e["windows"]
                if key not in w or "t" not in w or len(w["t"]) == 0:
                    continue
                t, y = np.asarray(w["t"], float), _floor(w[key])
                keep = t > 0
                if not keep.any():
                    continue
                color, marker = colors[e["integrator"]]
                ax.loglog(t[keep], y[keep], color=color, lw=1.0, label=e["label"])
                if e.get("failed"):
                    ax.plot(t[keep][-1], y[keep][-1], marker="x", ms=8, mew=2, color=color)
                drawn += 1
            if drawn:
                ax.set_xlabel("t")
                ax.set_ylabel(label)
                ax.set_title(label + " against t")
            else:
                _empty(ax, "no series: " + ("no conserved energy" if key == "energy"
                                            else "no run produced one"))
        handles, labels = axes[0, 0].get_legend_handles_labels()
        if not handles:
            handles, labels = axes[0, 1].get_legend_handles_labels()
        _arrange(fig, 1, 2, (handles, labels), ncols=3)
        fig.suptitle(title)
        return _svg(fig)


def standing(stands: list[Standing], colors: dict, title: str,
             winner: str | None = None) -> str:
    """Each method once, drift (left) and energy error (right) against its cost at matched
    accuracy, log-log.

    A filled marker is a run that reached the matched accuracy, a hollow one the method's
    most accurate run where it never did; a cross, a representative run that did not
    finish. The legend gives each method's drift and energy growth classes; ``winner`` (the
    named cost winner, if any) gets a black ring.
    """
    with rc_context(RC):
        fig, axes = _figure(1, 2, 9.0, 3.2)
        panels = (("drift", "max(|g|, |G v + g_t|)", "drift_class"),
                  ("energy", "max rel. energy error", "energy_class"))
        for ax, (attr, label, _) in zip(axes[0], panels):
            drawn = 0
            for st in stands:
                x, y = st.wall_s, getattr(st, attr)
                if not (math.isfinite(x) and x > 0 and math.isfinite(y)):
                    continue
                color, marker = colors[st.integrator]
                classes = "; ".join(f"{what} {getattr(st, cls)}" for what, _, cls in panels
                                    if getattr(st, cls))
                name = f"{st.integrator} ({classes})" if classes else st.integrator
                ax.loglog([x], _floor([y]), ls="none", ms=7, mew=1.2, color=color,
                          marker=marker if st.finished else "x",
                          mfc=color if st.reached else "none", label=name)
                if st.integrator == winner:
                    ax.loglog([x], _floor([y]), ls="none", marker="o", ms=14, mfc="none",
                              mec="k", mew=1.0, label="cost winner (wall time)")
                drawn += 1
            if drawn:
                ax.set_xlabel("wall time at matched accuracy [s]")
                ax.set_ylabel(label)
                ax.set_title(f"{label} against cost")
            else:
                _empty(ax, "no conserved energy" if attr == "energy" else
                       "no method reached a measured accuracy")
        entries = {}
        for ax in axes.flat:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                entries.setdefault(lab, h)
        # The winner's ring last, after the methods in their order.
        ring = [lab for lab in entries if lab.startswith("cost winner")]
        labels = [lab for lab in entries if lab not in ring] + ring
        _arrange(fig, 1, 2, ([entries[lab] for lab in labels], labels), ncols=2)
        fig.suptitle(title)
        return _svg(fig)


def overview(grid: dict[str, list[Standing]], winners: dict[str, str | None]) -> str:
    """Problems (rows) by methods (columns), each cell coloured by the drift class of the
    method's representative run and labelled with its drift (or "failed" where that run did
    not finish); a black frame marks the cost winner by wall time at matched accuracy.
    Blank: the method did not run the problem."""
    problems = list(grid)
    methods = sorted({st.integrator for stands in grid.values() for st in stands})
    with rc_context(RC):
        # Inches: the problem names at the left, the slanted method names above (about
        # 0.06 inch a character at 8 pt), the legend below in as many columns of
        # LEGEND_COLUMN inches as the figure holds (at least two); a cell is 0.62 x 0.3.
        chars = max(map(len, methods), default=0), max(map(len, problems), default=0)
        left, top = 0.3 + 0.06 * chars[1], 0.4 + 0.055 * chars[0]
        width = max(left + 0.2 + 0.62 * max(len(methods), 1), 0.3 + 2 * LEGEND_COLUMN)
        entries = len(CLASS_COLORS) + 1
        ncols = min(4, int((width - 0.3) / LEGEND_COLUMN))
        bottom = 0.3 + 0.2 * math.ceil(entries / ncols)
        height = top + bottom + 0.3 * max(len(problems), 1)
        fig, axes = _figure(1, 1, width, height)
        ax = axes[0, 0]
        ax.grid(False)
        for i, problem in enumerate(problems):
            for st in grid[problem]:
                j = methods.index(st.integrator)
                cls = st.drift_class if st.finished else "did not finish"
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1,
                                       color=CLASS_COLORS.get(cls, "#d9d9d9")))
                if not st.finished or math.isfinite(st.drift):
                    ax.text(j, i, fmt(st.drift, 1) if st.finished else "failed",
                            ha="center", va="center", fontsize=6)
                if winners.get(problem) == st.integrator:
                    ax.add_patch(Rectangle((j - 0.45, i - 0.45), 0.9, 0.9, fill=False,
                                           ec="k", lw=1.6))
        ax.set_xlim(-0.5, len(methods) - 0.5)
        ax.set_ylim(len(problems) - 0.5, -0.5)
        ax.set_xticks(range(len(methods)), methods, rotation=60, ha="right")
        ax.set_yticks(range(len(problems)), problems)
        ax.xaxis.tick_top()
        ax.tick_params(length=0)
        handles = [Rectangle((0, 0), 1, 1, color=c) for c in CLASS_COLORS.values()]
        handles.append(Rectangle((0, 0), 1, 1, fill=False, ec="k", lw=1.6))
        labels = [f"drift {k}" if k != "did not finish" else k for k in CLASS_COLORS]
        labels.append("cost winner (wall time)")
        fig.legend(handles, labels, loc="lower center", ncols=ncols)
        fig.subplots_adjust(left=left / width, right=1.0 - 0.2 / width, top=1.0 - top / height,
                            bottom=bottom / height)
        return _svg(fig)


def work_precision(runs, colors: dict, title: str, x: tuple[str, ...], y: tuple[str, ...],
                   floor: float = 0.0) -> str:
    """Precision metrics ``y`` (rows) against cost metrics ``x`` (columns), runs.csv column
    names, log-log, one line per integrator through its finished runs. A dashed line marks
    the reference floor ``floor`` in the final-error panels (errors below it are the
    reference's)."""
    with rc_context(RC):
        fig, axes = _figure(len(y), len(x), 4.0 * len(x), 2.85 * len(y))
        ok = runs[runs["status"] == Status.OK]
        for i, pcol in enumerate(y):
            for j, ccol in enumerate(x):
                ax = axes[i, j]
                drawn = 0
                for key, grp in ok.groupby("integrator"):
                    g = grp[[ccol, pcol]].astype(float).dropna()
                    g = g[g[ccol] > 0].sort_values(ccol)
                    if g.empty:
                        continue
                    color, marker = colors[key]
                    ax.loglog(g[ccol], _floor(g[pcol]), marker=marker, ms=4, lw=1.0,
                              color=color, label=key)
                    drawn += 1
                if drawn:
                    ax.set_xlabel(LABELS[ccol])
                    ax.set_ylabel(LABELS[pcol])
                    if pcol == "final_state_error" and floor > 0:
                        ax.axhline(floor, color="0.3", ls="--", lw=0.8,
                                   label=f"reference floor {fmt(floor)}")
                else:
                    _empty(ax, f"{LABELS[pcol]}: not measured" if pcol != "final_state_error"
                           else "final error: no reference")
        handles, labels = [], []
        for ax in axes.flat:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in labels:
                    handles.append(h)
                    labels.append(lab)
        _arrange(fig, len(y), len(x), (handles, labels), ncols=5)
        fig.suptitle(title)
        return _svg(fig)


def convergence(convs: list[Convergence], colors: dict, title: str, basis: str) -> str:
    """Error against step size, log-log (the report draws it when some run has a finite
    error), with fitted and nominal orders in the legend and a dashed slope of the nominal
    order through each method's finest fitted point. Points outside the asymptotic range
    (:func:`reports.analysis.fit`) are drawn hollow, those at the reference floor or
    round-off hollow and faint, and the reference floor as a dotted line."""
    with rc_context(RC):
        fig, axes = _figure(1, 1, 6.0, 4.2)
        ax = axes[0, 0]
        for c in convs:
            keep = np.isfinite(c.err)
            if not keep.any():
                continue
            color, marker = colors[c.integrator]
            fitted = "no fit" if math.isnan(c.order) else \
                f"fitted {c.order:.2f} over {c.n_fit} points"
            nominal = "n/a" if math.isnan(c.nominal) else fmt(c.nominal)
            ax.loglog(c.h[keep], _floor(c.err[keep]), lw=1.0, color=color,
                      label=f"{c.integrator}: {fitted}, nominal {nominal}")
            ax.loglog(c.h[c.fitted], _floor(c.err[c.fitted]), ls="none", marker=marker, ms=4,
                      color=color)
            # Outside the asymptotic range: hollow; at the floor or round-off: hollow, faint.
            outside = keep & ~c.fitted & c.usable
            ax.loglog(c.h[outside], _floor(c.err[outside]), ls="none", marker=marker, ms=5,
                      mfc="none", color=color)
            below = keep & ~c.usable
            ax.loglog(c.h[below], _floor(c.err[below]), ls="none", marker=marker, ms=5,
                      mfc="none", color=color, alpha=0.35)
            if not math.isnan(c.nominal) and c.fitted.any():
                h0, e0 = c.h[c.fitted][-1], c.err[c.fitted][-1]
                hs = np.array([c.h[keep][0], h0])
                ax.loglog(hs, e0 * (hs / h0) ** c.nominal, ls="--", lw=0.8, color=color)
        floor = max((c.floor for c in convs), default=0.0)
        if floor > 0:
            ax.axhline(floor, color="0.3", ls=":", lw=0.8, label=f"reference floor {fmt(floor)}")
        ax.set_xlabel("h")
        ax.set_ylabel("error")
        ax.legend(loc="best")
        # The basis names the reference and its floor: wrapped to the axis' width.
        ax.set_title(textwrap.fill(basis, 100), fontsize=7)
        _arrange(fig, 1, 1)
        fig.suptitle(title)
        return _svg(fig)


def history(hist: History) -> str:
    """The gate's metrics against commit, one small panel per metric, one grey line per run
    identity; red crosses mark the regressions of :class:`reports.analysis.History`."""
    metrics = list(hist.values)
    cols = min(3, len(metrics))
    rows = math.ceil(len(metrics) / cols)
    labels = list(hist.commits["label"])
    x = np.arange(len(labels))
    with rc_context(RC):
        fig, axes = _figure(rows, cols, 3.3 * cols, 2.6 * rows)
        for ax, metric in zip(axes.flat, metrics):
            frame = hist.values[metric]
            lower = gate.tolerance(metric).direction == "lower"
            values = frame.to_numpy(dtype=float)
            for line in values:
                if np.isfinite(line).any():
                    y = _floor(line) if lower else line
                    ax.plot(x, y, color="0.55", lw=0.7, marker=".", ms=3)
            bad = [(labels.index(c1), frame.loc[ident, c1]) for ident, m, _, c1, _
                   in hist.regressions if m == metric]
            if bad:
                bx, by = zip(*bad)
                by = np.asarray(by, dtype=float)
                ax.plot(bx, _floor(by) if lower else by, "x", color="tab:red", ms=7, mew=2,
                        label="regression")
            if lower and np.isfinite(values).any():
                ax.set_yscale("log")
            if not np.isfinite(values).any():
                _empty(ax, f"{label(metric)}: not measured")
                continue
            ax.set_xticks(x, labels, rotation=30, ha="right")
            ax.set_title(label(metric))
        for ax in list(axes.flat)[len(metrics):]:
            ax.set_visible(False)
        _arrange(fig, rows, cols)
        fig.subplots_adjust(hspace=0.7)
        return _svg(fig)


def scaling(panels: list[tuple[str, list[dict]]], colors: dict) -> str:
    """Time per step against N, log-log, one panel per problem and one line per family.

    ``panels``: ``(title, lines)`` with each line a dict of ``label``, ``key`` (the colour
    key; None draws the line black and dashed, for a yardstick), ``n`` and ``cost`` (the
    finished points). A dotted line of slope 1 through the lowest first point marks linear
    growth.
    """
    cols = max(1, len(panels))
    with rc_context(RC):
        fig, axes = _figure(1, cols, 4.5 * cols, 3.6)
        for ax, (title, lines) in zip(axes[0], panels):
            drawn = [line for line in lines if len(line["n"])]
            for line in drawn:
                if line["key"] is None:
                    ax.loglog(line["n"], line["cost"], color="k", ls="--", marker=".", ms=5,
                              lw=1.0, label=line["label"])
                else:
                    color, marker = colors[line["key"]]
                    ax.loglog(line["n"], line["cost"], color=color, marker=marker, ms=4,
                              lw=1.0, label=line["label"])
            if not drawn:
                _empty(ax, "no finished points")
                continue
            n0, c0 = min(((line["n"][0], line["cost"][0]) for line in drawn),
                          key=lambda p: p[1])
            n_max = max(max(line["n"]) for line in drawn)
            ns = np.array([n0, max(n_max, 2 * n0)], dtype=float)
            ax.loglog(ns, c0 * ns / n0, color="0.5", ls=":", lw=0.8, label="slope 1 (linear)")
            ax.set_xlabel("N")
            ax.set_ylabel("time per step [s]")
            ax.set_title(title)
        handles, labels = [], []
        for ax in axes.flat:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in labels:
                    handles.append(h)
                    labels.append(lab)
        _arrange(fig, 1, cols, (handles, labels), ncols=3)
        return _svg(fig)


def distributions(entries: list[dict], colors: dict, title: str) -> str:
    """Per-lane distributions of an ensemble's metrics: one box per run (``entries``: dicts
    with ``label``, ``integrator`` and ``lanes``, the per-lane table), one panel per metric
    (max |g|, max |G v + g_t|, max rel. energy error, and the final error where some lane
    has one, with the largest reference floor dashed), log scale, over the lanes that
    finished. Boxes span the quartiles, whiskers the extremes (every such lane is inside
    them), a line marks the median; each run keeps its row in every panel."""
    panels = [("max_pos_residual", "max |g| per lane"),
              ("max_vel_residual", "max |G v + g_t| per lane"),
              ("rel_energy_error", "max rel. energy error per lane")]
    finals = [np.asarray(e["lanes"].get("final_state_error", []), dtype=float)
              for e in entries]
    if any(np.isfinite(final).any() for final in finals):
        panels.append(("final_state_error", "final error per lane"))
    rows = range(1, len(entries) + 1)
    with rc_context(RC):
        fig, axes = _figure(1, len(panels), 12.0, 3.0 + 0.12 * len(entries))
        for ax, (column, label) in zip(axes[0], panels):
            data, places, shades = [], [], []
            for row, entry in zip(rows, entries):
                ok = np.asarray(entry["lanes"]["status"]) == 0
                values = _floor(np.asarray(entry["lanes"][column])[ok])
                values = values[np.isfinite(values)]
                if len(values):
                    data.append(values)
                    places.append(row)
                    shades.append(colors[entry["integrator"]][0])
            ax.set_yticks(rows, [e["label"] for e in entries] if ax is axes[0, 0]
                          else [""] * len(entries))
            ax.set_ylim(0.5, len(entries) + 0.5)
            ax.set_xlabel(label)
            if not data:
                _empty(ax, f"{label}: not measured")
                continue
            boxes = ax.boxplot(data, positions=places, orientation="horizontal",
                               whis=(0, 100), widths=0.6, patch_artist=True,
                               manage_ticks=False, medianprops={"color": "black"})
            for patch, shade in zip(boxes["boxes"], shades):
                patch.set_facecolor(shade)
                patch.set_alpha(0.7)
            ax.set_xscale("log")
            if column == "final_state_error":
                floors = [np.asarray(e["lanes"].get("reference_floor", []), dtype=float)
                          for e in entries]
                floor = max((np.nanmax(f) for f in floors if np.isfinite(f).any()),
                            default=0.0)
                if floor > 0:
                    ax.axvline(floor, color="0.3", ls="--", lw=0.8)
                    ax.annotate(f"reference floor {fmt(floor)}", (floor, 1.0),
                                xycoords=("data", "axes fraction"), fontsize=7,
                                ha="left", va="bottom", color="0.3")
        side = 0.07 * max((len(e["label"]) for e in entries), default=0)
        width, height = fig.get_size_inches()
        fig.set_size_inches(width + side, height)
        fig.subplots_adjust(left=(0.3 + side) / (width + side), right=0.98, top=0.85,
                            bottom=0.2, wspace=0.15)
        fig.suptitle(title)
        return _svg(fig)


#: What an ensemble's work-precision panel shows, the first that every run with a lane that
#: finished has: the final error, else the max rel. energy error, else max |g| (short name
#: of the :class:`Spread` columns and the axis label).
ENSEMBLE_PRECISION = (("final", "final error"), ("energy", "max rel. energy error"),
                      ("pos", "max |g|"))


def ensemble_cost(runs, colors: dict, title: str) -> str:
    """Two panels per ensemble sweep: the median lane's final error (or max rel. energy
    error, or max |g|: :data:`ENSEMBLE_PRECISION`) against wall time per lane, with a band
    and a bar at each run from the best lane to the worst; and the fraction of lanes that
    failed against ``h`` (or rtol)."""
    with rc_context(RC):
        fig, axes = _figure(1, 2, 8.0, 3.0)
        accuracy, failures = axes[0]
        finished = runs["pos_q50"].notna()
        metric, name = next(((m, n) for m, n in ENSEMBLE_PRECISION
                             if runs.loc[finished, f"{m}_q50"].notna().all()),
                            ENSEMBLE_PRECISION[-1])
        drawn = False
        for key, grp in runs.groupby("integrator"):
            color, marker = colors[key]
            setting = grp["h"].where(grp["h"].notna(), grp["rtol"]).astype(float)
            order = np.argsort(setting.to_numpy())
            grp, setting = grp.iloc[order], setting.iloc[order]
            failures.semilogx(setting, grp["failed_fraction"].astype(float), marker=marker,
                              ms=4, lw=1.0, color=color, label=key)
            done = grp[grp[f"{metric}_q50"].notna()]
            if done.empty:
                continue
            cost = done["wall_s"].astype(float) / done["lanes"].astype(float)
            cost_order = np.argsort(cost.to_numpy())
            done, cost = done.iloc[cost_order], cost.iloc[cost_order]
            best, worst = _floor(done[f"{metric}_q0"]), _floor(done[f"{metric}_q100"])
            accuracy.fill_between(cost, best, worst, color=color, alpha=0.2, lw=0)
            # A bar at each run too: a method run at one setting has no band to fill.
            accuracy.vlines(cost, best, worst, color=color, alpha=0.5, lw=2)
            accuracy.loglog(cost, _floor(done[f"{metric}_q50"]), marker=marker, ms=4, lw=1.0,
                            color=color, label=key)
            drawn = True
        if drawn:
            accuracy.set_xlabel("wall time per lane [s]")
            accuracy.set_ylabel(f"median lane: {name}\n(band and bars: best to worst)")
        else:
            _empty(accuracy, "no lane finished")
        failures.set_xlabel("h (or rtol)")
        failures.set_ylabel("fraction of lanes failed")
        failures.set_ylim(-0.05, 1.05)
        handles, labels = failures.get_legend_handles_labels()
        _arrange(fig, 1, 2, (handles, labels), ncols=5)
        fig.suptitle(title)
        return _svg(fig)

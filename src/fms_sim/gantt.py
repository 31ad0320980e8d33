"""Gantt charts of schedules: machines, AGVs and tool transporters on one time axis.

The chart has three sections, each with a labelled header band:

* one row per machine (``M1``..``Mm``) with operation bars coloured by job and labelled ``j.k``;
* one row per AGV (``AGV0``..) split in two lanes: loaded trips (upper lane, coloured by the job they carry,
  labelled ``j.k`` = the operation the part is delivered to) and empty deadheading trips (lower, thinner lane,
  grey and hatched), so an empty trip can never be mistaken for a loaded one;
* one row per tool transporter (``TT0``..) with the same two lanes; loaded trips are coloured by the job
  whose operation the tool serves and labelled with the tool (``T3``).

A dashed vertical line marks the makespan; breakdowns and outages that the schedule's ``meta["scenario"]`` records
are shaded on their rows, and the default title (:func:`chart_title`) says what disrupted the run. Rendering uses
:class:`matplotlib.figure.Figure` with an explicit Agg canvas, so it works headless and never touches pyplot's global
state (callers need no ``matplotlib.use``). Bars are drawn as one ``PolyCollection`` per kind and labels only where
they fit, so thousands of bars render in about a second.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator
from matplotlib.transforms import blended_transform_factory

from .files import replacing
from .instance import MAX_COUNT, Instance, require_instance
from .schedule import Schedule, require_schedule

__all__ = ["chart_title", "plot_gantt", "save_gantt", "chart_formats"]

# Layout constants, in row units (vertical) and inches (margins). Fixed margins (instead of tight_layout) keep
# the geometry known before drawing, which the label-fitting test relies on, and avoid an extra render pass.
_HEADER = 0.9          # height of a section header band, in row units
_OP_HALF = 0.38        # machine bars span y +- this
_LOADED = (-0.40, 0.14)  # loaded-trip lane of a vehicle row (offsets from the row centre; y grows downwards)
_EMPTY = (0.20, 0.40)    # empty-trip lane of a vehicle row
_LEFT_IN, _RIGHT_IN, _TOP_IN, _BOTTOM_IN = 0.8, 0.3, 0.75, 0.6
_DPI = 110
_LABEL_FS = 7.0
_MAX_LABELS = 2500     # safety cap on text artists (each costs render time)
_EMPTY_FACE = "#dcdcdc"
_EMPTY_EDGE = "#6e6e6e"


@dataclass(frozen=True)
class _Row:
    """One chart row: its tick label, its kind (``"machine"``, ``"agv"``, ``"tt"``), index and y centre."""

    label: str
    kind: str
    index: int
    y: float


def _palette(n_jobs: int) -> list[tuple[float, float, float, float]]:
    """Qualitative job colours: ``tab10`` for few jobs, else tab20/tab20b/tab20c without their greys and near-greys
    (53 colours, then cycling). The greys are left out: the lightest was all but the empty trips' grey, and a grey
    job reads as no job. Within tab20 the darker member of each pair comes first, so the first jobs differ in hue;
    tab20b and tab20c come in shades of a few hues."""
    def grey(c: tuple[float, float, float, float]) -> bool:
        return max(c[:3]) - min(c[:3]) < 0.1

    if n_jobs <= 10:
        tab10 = colormaps["tab10"].colors  # type: ignore[attr-defined]
        return [c for c in map(to_rgba, tab10) if not grey(c)]
    cols: list[tuple[float, float, float, float]] = []
    for name in ("tab20", "tab20b", "tab20c"):
        cmap_cols = colormaps[name].colors  # type: ignore[attr-defined]
        cols += [to_rgba(c) for c in cmap_cols[0::2]] + [to_rgba(c) for c in cmap_cols[1::2]]
    return [c for c in cols if not grey(c)]


def _text_colour(rgba: Sequence[float]) -> str:
    """Black or white, whichever reads better on ``rgba`` (by relative luminance)."""
    r, g, b = rgba[:3]
    return "black" if 0.299 * r + 0.587 * g + 0.114 * b > 0.55 else "white"


def _layout(schedule: Schedule, instance: Instance | None, machines: int | None = None
            ) -> tuple[list[_Row], list[tuple[str, float, float]], float]:
    """Rows and sections (name, header centre, section start) top-down, and the total height in row units; at least
    ``machines`` machine rows when given."""
    # (one row per number up to the largest: machine 5000 took 14 s and 720 MB, 10**6 was killed at 24 GB; no
    # instance has more than MAX_COUNT of each)
    bad = ([f"machine {r.machine}" for r in schedule.operations if not 1 <= r.machine <= MAX_COUNT]
           + [f"AGV {t.agv}" for t in schedule.agv_trips if not 0 <= t.agv < MAX_COUNT]
           + [f"tool transporter {t.transporter}" for t in schedule.tool_trips if not 0 <= t.transporter < MAX_COUNT])
    if bad:
        raise ValueError(f"cannot plot: the schedule names {bad[0]}, which does not exist")
    for n, what in ((schedule.n_agvs, "AGVs"), (schedule.n_tool_transporters, "tool transporters")):
        if n > MAX_COUNT:
            raise ValueError(f"cannot plot: the schedule declares {n} {what}, more than an instance has "
                             f"(at most {MAX_COUNT})")
    n_m = max(r.machine for r in schedule.operations)
    n_agv = max([schedule.n_agvs] + [t.agv + 1 for t in schedule.agv_trips])
    n_tt = max([schedule.n_tool_transporters] + [t.transporter + 1 for t in schedule.tool_trips])
    if machines is not None:
        n_m = max(n_m, machines)
    if instance is not None:
        n_m = max(n_m, instance.n_machines)
        n_agv = max(n_agv, instance.n_agvs)
        n_tt = max(n_tt, instance.n_tool_transporters)
    sections = [("Machines", "machine", "M", 1, n_m),
                ("AGVs  (upper lane: loaded, lower lane: empty)", "agv", "AGV", 0, n_agv),
                ("Tool transporters  (upper lane: loaded, lower lane: empty)", "tt", "TT", 0, n_tt)]
    rows: list[_Row] = []
    heads: list[tuple[str, float, float]] = []
    y = 0.0
    for title, kind, prefix, first, count in sections:
        if count <= 0:
            continue
        heads.append((title, y + _HEADER / 2, y))
        y += _HEADER
        for i in range(first, first + count):
            rows.append(_Row(f"{prefix}{i}", kind, i, y + 0.5))
            y += 1.0
    return rows, heads, y


_DOWN_FACE, _DOWN_EDGE = (0.9, 0.3, 0.25, 0.18), "#c0392b"


def _recorded(scenario: Any, key: str) -> list[dict[str, Any]]:
    """The windows (``breakdowns`` or ``outages``) of a scenario as a schedule's ``meta`` records it; a malformed record
    (outages as a string, no scenario object) gives none, as no record."""
    items = scenario.get(key) if isinstance(scenario, dict) else None
    return [d for d in items if isinstance(d, dict)] if isinstance(items, list) else []


def _downtime(schedule: Schedule, row_y: dict[tuple[str, int], float]) -> list[tuple[float, float, float, float]]:
    """Spans of the breakdowns and outages that ``schedule.meta["scenario"]`` records, on their rows (those that begin
    before the makespan: one after it disrupted nothing and lies off the time axis)."""
    sc = schedule.meta.get("scenario")
    out: list[tuple[float, float, float, float]] = []
    windows: list[tuple[Any, Any, Any, Any]] = [("machine", b.get("machine"), b.get("start"), b.get("duration"))
                                                 for b in _recorded(sc, "breakdowns")]
    windows += [(o.get("kind"), o.get("vehicle"), o.get("start"), o.get("duration")) for o in _recorded(sc, "outages")]
    for kind, i, start, dur in windows:
        y = row_y.get((kind, i))
        if y is not None and isinstance(start, int) and isinstance(dur, int) and start < schedule.makespan:
            out.append((start, start + dur, y - 0.48, y + 0.48))
    return out


def chart_title(schedule: Schedule, run: str | None = None) -> str:
    """The chart's default title: the instance, the run (when given), the makespan, what the run was disrupted
    by, as its ``meta["scenario"]`` records it (``"ra01 — makespan 120 (under disruptions: 1 breakdown, 1 outage,
    noise 0.1)"``), so that a disrupted run's chart is not read as a nominal one, and the jobs that live orders
    brought (``meta["arrivals"]``: ``"; 2 jobs ordered during the run, from time 32"``), whose idle start is
    otherwise unexplained."""
    middle = f" — run {run}" if run is not None else ""
    notes = _disruption_note(schedule) + _orders_note(schedule)
    return f"{schedule.instance}{middle} — makespan {schedule.makespan}{notes}"


def _orders_note(schedule: Schedule) -> str:
    """The jobs live orders brought, as ``meta["arrivals"]`` records them (``[job, time]`` pairs); empty for none."""
    arrivals = schedule.meta.get("arrivals")
    times = [a[1] for a in arrivals if isinstance(a, (list, tuple)) and len(a) == 2 and isinstance(a[1], int)
             and not isinstance(a[1], bool)] if isinstance(arrivals, list) else []
    if not times:
        return ""
    n = len(times)
    return f"; {n} job{'' if n == 1 else 's'} ordered during the run, from time {min(times)}"


def _disruption_note(schedule: Schedule) -> str:
    """What the recorded scenario disrupted the run with (``" (under disruptions: 1 breakdown, noise 0.1)"``);
    empty for a nominal run. A malformed record says only what it can."""
    sc = schedule.meta.get("scenario")
    if not isinstance(sc, dict):
        return ""
    parts = []
    for key, one in (("breakdowns", "breakdown"), ("outages", "outage")):
        # (one that begins at or after the makespan disrupted nothing: it was counted, and drawn off the axis)
        n = sum(1 for d in _recorded(sc, key) if not isinstance(d.get("start"), int)
                or d["start"] < schedule.makespan)
        if n:
            parts.append(f"{n} {one}{'' if n == 1 else 's'}")
    noise = sc.get("noise")
    if isinstance(noise, (int, float)) and not isinstance(noise, bool) and noise > 0:
        parts.append(f"noise {noise:g}")
    return f" (under disruptions: {', '.join(parts)})" if parts else ""


def _rects(spans: Iterable[tuple[float, float, float, float]]) -> np.ndarray:
    """``(x0, x1, y0, y1)`` spans as an ``(N, 4, 2)`` array of rectangle vertices for a PolyCollection."""
    a = np.asarray(list(spans), dtype=float).reshape(-1, 4)
    x0, x1, y0, y1 = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    return np.stack([np.stack([x0, y0], 1), np.stack([x1, y0], 1),
                     np.stack([x1, y1], 1), np.stack([x0, y1], 1)], 1)


def plot_gantt(schedule: Schedule, instance: Instance | None = None, path: str | Path | None = None, *,
               title: str | None = None, machines: int | None = None) -> Figure:
    """Draw ``schedule`` as a Gantt chart and return the figure; also save it to ``path`` when given.

    ``instance`` (optional) only widens the chart to rows the schedule leaves idle (all of its machines,
    AGVs and transporters); ``machines`` (optional, the shop's machine count where the instance is not at hand: the
    recorder's charts) widens it to that many machine rows. The file format follows the suffix of ``path`` (PNG for
    none, or for one that matplotlib does not write).
    Raises ``ValueError("empty schedule")`` when the schedule has no operations.
    """
    require_schedule(schedule, "plot_gantt")  # (an instance in its place, the arguments swapped: AttributeError)
    if instance is not None:
        require_instance(instance, "plot_gantt's instance")
    if machines is not None and not (isinstance(machines, int) and not isinstance(machines, bool)
                                     and 1 <= machines <= MAX_COUNT):
        raise ValueError(f"machines must be an integer from 1 to {MAX_COUNT}, got {machines!r}")
    if not schedule.operations:
        raise ValueError("empty schedule")
    rows, heads, total = _layout(schedule, instance, machines)
    row_y = {(r.kind, r.index): r.y for r in rows}
    n_jobs = max(max(o.job for o in schedule.operations) + 1, instance.n_jobs if instance is not None else 0)
    palette = _palette(n_jobs)

    def colour(job: int | None) -> tuple[float, float, float, float]:
        return palette[job % len(palette)] if job is not None else to_rgba("#9e9e9e")

    # Time span and figure geometry.
    t_end = max([schedule.makespan]
                + [o.end for o in schedule.operations]
                + [t.end for t in schedule.agv_trips]
                + [t.end for t in schedule.tool_trips])
    t_start = min([0] + [o.start for o in schedule.operations] + [t.start for t in schedule.agv_trips]
                  + [t.start for t in schedule.tool_trips])
    span = max(t_end - t_start, 1)
    # (at least one time unit: a chart of zero-duration operations at time 0 had an axis of -0.01..0.02)
    x_lo, x_hi = t_start - 0.01 * span, max(t_end, t_start + 1) + 0.02 * span
    lane_counts = [sum(1 for o in schedule.operations if o.machine == r.index) for r in rows if r.kind == "machine"]
    lane_counts += [sum(1 for t in schedule.agv_trips if t.loaded) // max(1, schedule.n_agvs)]
    lane_counts += [sum(1 for t in schedule.tool_trips if t.loaded) // max(1, schedule.n_tool_transporters)]
    width_in = float(np.clip(9.0 + 0.045 * max(lane_counts), 11.0, 22.0))
    row_in = float(np.clip(10.0 / total, 0.2, 0.34))
    height_in = max(3.2, total * row_in + _TOP_IN + _BOTTOM_IN)
    fig = Figure(figsize=(width_in, height_in), dpi=_DPI)
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=_LEFT_IN / width_in, right=1 - _RIGHT_IN / width_in,
                        top=1 - _TOP_IN / height_in, bottom=_BOTTOM_IN / height_in)
    ax = fig.add_subplot()
    ax.set_xlim(x_lo, x_hi)
    ax.set_ylim(total, 0)  # top-down
    ax_w_pt = (width_in - _LEFT_IN - _RIGHT_IN) * 72.0
    ax_h_pt = (height_in - _TOP_IN - _BOTTOM_IN) * 72.0
    pt_per_t = ax_w_pt / (x_hi - x_lo)
    pt_per_row = ax_h_pt / total

    labels: list[tuple[float, float, str, str, float]] = []  # x, y, text, colour, fontsize
    # Dark outlines separate adjacent bars, but on narrow bars they would drown the job colours.
    widths = [o.end - o.start for o in schedule.operations]
    edge_lw = 0.4 if float(np.median(widths)) * pt_per_t >= 6.0 else 0.0

    def maybe_label(x0: float, x1: float, y: float, h: float, text: str, face: Sequence[float]) -> None:
        fs = min(_LABEL_FS, 0.72 * h * pt_per_row)
        if fs < 4.5:
            return
        if (x1 - x0) * pt_per_t >= 0.62 * fs * len(text) + 3.0:
            labels.append(((x0 + x1) / 2, y, text, _text_colour(face), fs))

    # Machines. An operation of zero duration is drawn 2 points wide about its instant: a zero-width bar was at most
    # a hairline without its job's colour, or hidden under a neighbour's outline.
    half = 1.0 / pt_per_t
    spans, faces = [], []
    for o in schedule.operations:
        y = row_y[("machine", o.machine)]
        x0, x1 = (o.start, o.end) if o.end > o.start else (o.start - half, o.start + half)
        spans.append((x0, x1, y - _OP_HALF, y + _OP_HALF))
        faces.append(colour(o.job))
        maybe_label(o.start, o.end, y, 2 * _OP_HALF, f"{o.job}.{o.op}", faces[-1])
    ax.add_collection(PolyCollection(_rects(spans), facecolors=faces, edgecolors="#303030", linewidths=edge_lw))

    # Vehicles: loaded trips in the upper lane, empty trips (hatched grey) in the lower lane.
    loaded_spans, loaded_faces, empty_spans = [], [], []
    trips = [("agv", t.agv, t.loaded, t.job, f"{t.job}.{t.op}", t.start, t.end) for t in schedule.agv_trips]
    trips += [("tt", t.transporter, t.loaded, t.job, f"T{t.tool}", t.start, t.end) for t in schedule.tool_trips]
    for kind, v, loaded, job, text, s, e in trips:
        y = row_y[(kind, v)]
        if loaded:
            loaded_spans.append((s, e, y + _LOADED[0], y + _LOADED[1]))
            loaded_faces.append(colour(job))
            maybe_label(s, e, y + sum(_LOADED) / 2, _LOADED[1] - _LOADED[0], text, loaded_faces[-1])
        else:
            empty_spans.append((s, e, y + _EMPTY[0], y + _EMPTY[1]))
    if loaded_spans:
        ax.add_collection(PolyCollection(_rects(loaded_spans), facecolors=loaded_faces, edgecolors="#303030",
                                         linewidths=edge_lw))
    if empty_spans:
        ax.add_collection(PolyCollection(_rects(empty_spans), facecolors=_EMPTY_FACE, edgecolors=_EMPTY_EDGE,
                                         linewidths=0.4, hatch="/////"))

    # Disruptions recorded with the schedule: machines down and vehicles out of service, as translucent red hatched
    # bands over the bars of their row (below the labels), so that an operation a breakdown suspends shows its pause
    # (drawn behind, the band was hidden by the bar, which read as running straight through).
    down = _downtime(schedule, row_y)
    if down:
        ax.add_collection(PolyCollection(_rects(down), facecolors=_DOWN_FACE, edgecolors=_DOWN_EDGE, linewidths=0.6,
                                         hatch="xxx", zorder=1.5))

    for x, y, text, col, fs in labels[:_MAX_LABELS]:  # (past the cap the operations' come first; all were dropped)
        ax.text(x, y, text, ha="center", va="center", fontsize=fs, color=col, clip_on=True)

    # Sections: separators and header bands with their names.
    left_edge = blended_transform_factory(ax.transAxes, ax.transData)
    for name, yc, y0 in heads:
        ax.axhspan(y0, y0 + _HEADER, color="#f2f2f2", zorder=0, lw=0)
        if y0 > 0:
            ax.axhline(y0, color="#7a7a7a", lw=1.0)
        ax.text(0.004, yc, name, transform=left_edge, ha="left", va="center", fontsize=8.5, fontweight="bold",
                color="#333333")

    # Makespan line with its value (right-aligned so it never leaves the axes).
    ax.axvline(schedule.makespan, color="#c0392b", ls="--", lw=1.2, zorder=5)
    ax.text(schedule.makespan, heads[0][1], f"makespan {schedule.makespan} ", ha="right", va="center",
            fontsize=8.5, color="#c0392b", fontweight="bold", zorder=6)

    # Axes cosmetics.
    ax.set_yticks([r.y for r in rows], [r.label for r in rows], fontsize=8)
    ax.tick_params(axis="y", length=0)
    ax.xaxis.set_major_locator(MaxNLocator(nbins=min(30, max(6, int(width_in * 1.2))), integer=True))
    ax.tick_params(axis="x", labelsize=8)
    ax.grid(axis="x", color="#d0d0d0", lw=0.5, zorder=0)
    ax.set_axisbelow(True)
    ax.set_xlabel("time")
    handles = [Patch(facecolor=colour(0), edgecolor="#303030", lw=0.4, label="operation / loaded trip (colour = job)"),
               Patch(facecolor=_EMPTY_FACE, edgecolor=_EMPTY_EDGE, hatch="/////", lw=0.4,
                     label="empty trip (deadheading)"),
               Line2D([], [], color="#c0392b", ls="--", lw=1.2, label="makespan")]
    if not schedule.agv_trips and not schedule.tool_trips:
        handles = [handles[0], handles[2]]
        handles[0] = Patch(facecolor=colour(0), edgecolor="#303030", lw=0.4, label="operation (colour = job)")
    if down:
        handles.insert(-1, Patch(facecolor=_DOWN_FACE, edgecolor=_DOWN_EDGE, hatch="xxx", lw=0.6,
                                 label="down / out of service"))
    ax.legend(handles=handles, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=len(handles), frameon=False,
              fontsize=8, handlelength=2.2, borderaxespad=0.2)
    text, size = _fitted_title(title if title is not None else chart_title(schedule), width_in - _LEFT_IN - 0.1)
    fig.text(_LEFT_IN / width_in, 1 - 0.12 / height_in, text, ha="left", va="top", fontsize=size,
             fontweight="bold", parse_math=False)  # a name with "$...$" is text (unbalanced: a parse error)

    if path is not None:
        _save(fig, Path(path))
    return fig


def _fitted_title(title: str, width_in: float) -> tuple[str, float]:
    """The title and its font size for a line ``width_in`` inches wide: 11 points, smaller down to 8 where it is long,
    then wrapped onto a second line (a long run id and a disruption note ran off the chart, the note cut off). The
    width of a bold character is taken as 0.72 of the size (DejaVu Sans Bold: most letters narrower)."""
    import textwrap

    chars = len(title)
    size = min(11.0, max(8.0, width_in * 72.0 / (0.72 * max(chars, 1))))
    fit = int(width_in * 72.0 / (0.72 * size))
    return (title if chars <= fit else textwrap.fill(title, width=fit, max_lines=2, placeholder=" ...")), size


def _save(fig: Figure, out: Path) -> None:
    """Write ``fig`` to ``out`` in the format its suffix names where matplotlib writes it (png, pdf, svg, eps, ...),
    else PNG, through a temporary file, so that a failed write leaves an existing chart as it was."""
    fmt = out.suffix[1:].lower()
    if out.is_dir():  # (an IsADirectoryError naming the temporary file)
        raise ValueError(f"cannot write the chart: {out} is a folder; name a file")
    with replacing(out) as tmp:
        fig.savefig(tmp, dpi=_DPI, format=fmt if fmt in chart_formats() else "png")


#: matplotlib formats a chart is not written as: pgf needs a LaTeX installation (it was accepted, and the run then
#: ended in a traceback after its solve)
_NOT_CHARTS = frozenset({"pgf"})


def chart_formats() -> list[str]:
    """The file suffixes (without the dot) a chart can be written as: matplotlib's formats (png, pdf, svg, ...) but
    those that need more than matplotlib (pgf: LaTeX)."""
    return sorted(set(FigureCanvasAgg.get_supported_filetypes()) - _NOT_CHARTS)


def save_gantt(schedule: Schedule, path: str | Path, instance: Instance | None = None,
               title: str | None = None, machines: int | None = None) -> Path:
    """Render ``schedule`` (see :func:`plot_gantt`) to ``path`` and return it: in the format its suffix names
    (a PDF for ``.pdf``, an SVG for ``.svg``, ...), a PNG for any suffix matplotlib does not write."""
    out = Path(path)
    _save(plot_gantt(schedule, instance, title=title, machines=machines), out)
    return out

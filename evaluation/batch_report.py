"""The tables and the report of a batch of runs (``slam batch``): one row per log × setting.

Writes into the batch folder, each file atomically:

* ``results.csv`` — a header, then one line per run; missing numbers empty;
* ``results.json`` — ``{"columns", "rows", **meta}``, missing numbers null;
* ``results.md`` — the main columns as a Markdown table;
* ``report.html`` — that table, a bar chart of the relation error per log beside Cartographer's published
  figure (Hess et al., ICRA 2016, Table II, :mod:`evaluation.published`), the loop-closure precision per
  log (Cartographer's 20 cm / 1° criterion, Hess et al. 2016 §VI-B), and for every swept value the
  relation error and the precision against it, one line per log (matplotlib, figures inline as PNG).

A row has the keys of :data:`RESULT_KEYS`; ``values`` maps each config value the setting changed
(dotted name) to its value and becomes one column per name, after ``setting``. ``status`` is ``ok``
or ``failed: <one-line error>``.
"""

from __future__ import annotations

import base64
import csv
import html
import json
import math
import os
from pathlib import Path
from typing import Any, Sequence

from core.atomic import atomic_open

__all__ = ["RESULT_KEYS", "columns", "flat_rows", "markdown_table", "write_results"]

#: Keys of a batch row, in table order.
RESULT_KEYS = ("log", "setting", "values", "status", "relation_trans_mean_m", "relation_rot_mean_deg", "relations_used",
               "cartographer_trans_mean_m", "cartographer_rot_mean_deg", "ape_rmse_m", "loops_accepted", "loops_pruned",
               "loop_precision", "self_check", "self_check_contradicting", "scans", "keyframes", "wall_time_s", "peak_memory_mb", "run_dir", "log_path",
               "trajectory_sha256", "resumed")

# Markdown / HTML: (key, header, format)
_SHOWN = (("relation_trans_mean_m", "relation error [m]", "{:.4f}"), ("relation_rot_mean_deg", "[deg]", "{:.3f}"),
          ("cartographer_trans_mean_m", "Cartographer [m]", "{:.4f}"), ("cartographer_rot_mean_deg", "[deg]", "{:.3f}"),
          ("ape_rmse_m", "APE RMSE [m]", "{:.4f}"), ("loops_accepted", "closures", "{}"), ("loops_pruned", "pruned", "{}"),
          ("loop_precision", "precision", "{:.2%}"), ("self_check", "self-check", "{}"),
          ("self_check_contradicting", "contradicting / checked keyframes", "{}"), ("keyframes", "keyframes", "{}"), ("wall_time_s", "wall [s]", "{:.1f}"),
          ("peak_memory_mb", "peak [MB]", "{:.0f}"))


def columns(value_names: Sequence[str]) -> list[str]:
    """The flat columns: ``log, setting``, the changed values by name, then the rest of :data:`RESULT_KEYS`."""
    return ["log", "setting", *value_names, *[k for k in RESULT_KEYS if k not in ("log", "setting", "values")]]


def _clean(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def flat_rows(rows: Sequence[dict[str, Any]], value_names: Sequence[str]) -> list[dict[str, Any]]:
    """Rows with ``values`` spread into one key per changed value (None where a setting leaves it alone)."""
    cols = columns(value_names)
    out = []
    for r in rows:
        vals = r.get("values") or {}
        flat = {k: vals.get(k) for k in value_names} | {k: v for k, v in r.items() if k != "values"}
        out.append({c: _clean(flat.get(c)) for c in cols})
    return out


def _cell(v: Any, fmt: str = "{}") -> str:
    if v is None:
        return "–"
    try:
        return fmt.format(v)
    except (ValueError, TypeError):
        return str(v)


def _value(v: Any) -> str:
    return "–" if v is None else (f"{v:g}" if isinstance(v, float) else str(v))


def markdown_table(rows: Sequence[dict[str, Any]], value_names: Sequence[str]) -> str:
    """The main columns of *rows* (flat, :func:`flat_rows`) as a Markdown table."""
    head = ["log", "setting", *value_names, "status", *[h for _, h, _ in _SHOWN]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(r["log"]), str(r["setting"]), *[_value(r.get(n)) for n in value_names],
                 str(r["status"]).replace("|", "\\|"), *[_cell(r.get(k), f) for k, _, f in _SHOWN]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _html_table(rows: Sequence[dict[str, Any]], value_names: Sequence[str]) -> str:
    head = ["log", "setting", *value_names, "status", *[h for _, h, _ in _SHOWN]]
    out = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in rows:
        status = str(r["status"])
        cls = "" if status == "ok" else ' class="failed"'
        cells = [str(r["log"]), str(r["setting"]), *[_value(r.get(n)) for n in value_names], status,
                 *[_cell(r.get(k), f) for k, _, f in _SHOWN]]
        out.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "\n".join(out) + "</table>"


def _figures(rows: Sequence[dict[str, Any]], value_names: Sequence[str], sweeps: dict[str, list[Any]]) -> list[tuple[str, bytes, str]]:
    """(title, PNG, caption) of the report's figures (module docstring)."""
    from . import plots

    ok = [r for r in rows if r["status"] == "ok"]
    figs = []
    logs = list(dict.fromkeys(r["log"] for r in ok))
    rel = {g: {r["setting"]: r["relation_trans_mean_m"] for r in ok if r["log"] == g} for g in logs}
    rel = {g: v for g, v in rel.items() if any(x is not None for x in v.values())}
    if rel:
        cart = {r["log"]: r["cartographer_trans_mean_m"] for r in ok if r["cartographer_trans_mean_m"] is not None}
        figs.append(("Relation error per log", plots.grouped_bars_png(
            rel, "relation error, mean translation [m]", "Kümmerle relation error per log",
            cart, "Cartographer (Hess et al. 2016)"),
            "Mean translational relation error of each run (one bar per setting) beside Cartographer's published "
            "figure, where the log is one of the Kümmerle benchmark's."))
    prec = {g: {r["setting"]: r["loop_precision"] for r in ok if r["log"] == g} for g in logs}
    prec = {g: v for g, v in prec.items() if any(x is not None for x in v.values())}
    if prec:
        figs.append(("Loop-closure precision per log", plots.grouped_bars_png(
            prec, "precision (consistent after optimisation)", "Loop-closure precision per log"),
            "Fraction of the closures the verifier accepted that the final solution violates by at most 20 cm and 1° "
            "(the ones the back end pruned count as violated)."))
    for name in sweeps:
        others = [n for n in value_names if n != name]
        for key, label in (("relation_trans_mean_m", "relation error [m]"), ("loop_precision", "loop-closure precision")):
            series: dict[str, list[tuple[float, float]]] = {}
            for r in ok:
                if r.get(name) is None or r.get(key) is None:
                    continue
                fixed = ", ".join(f"{n}={_value(r.get(n))}" for n in others if r.get(n) is not None)
                series.setdefault(r["log"] + (f" ({fixed})" if fixed else ""), []).append((float(r[name]), float(r[key])))
            if series:
                figs.append((f"{label} against {name}", plots.lines_png(series, name, label, f"{label} against {name}"),
                             "One line per log (and per value of the other swept settings)."))
    return figs


def _html(rows: Sequence[dict[str, Any]], value_names: Sequence[str], meta: dict[str, Any]) -> str:
    figs = "\n".join(
        f'<figure><h2>{html.escape(t)}</h2><img alt="{html.escape(t)}" '
        f'src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}"/>'
        f"<figcaption>{html.escape(c)}</figcaption></figure>"
        for t, png, c in _figures(rows, value_names, meta.get("sweeps") or {}))
    n_failed = sum(1 for r in rows if r["status"] != "ok")
    facts = (f"{len(rows)} runs: {len(rows) - n_failed} ok, {n_failed} failed, {meta.get('resumed', 0)} taken from an "
             f"earlier batch (same log and config hash). Spec: {meta.get('spec', '')}.")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>gpslam batch report</title>
<style>
body {{ font-family: sans-serif; max-width: 1200px; margin: 2em auto; color: #222; }}
table {{ border-collapse: collapse; font-size: 0.85em; margin-bottom: 1em; }}
td, th {{ border-bottom: 1px solid #ddd; padding: 2px 10px 2px 2px; font-family: monospace; text-align: left; }}
tr.failed td {{ color: #b00; }}
figure {{ margin: 2em 0; }} img {{ max-width: 100%; }} figcaption {{ color: #555; }}
</style></head><body>
<h1>gpslam batch report</h1>
<p>{html.escape(facts)}</p>
{_html_table(rows, value_names)}
{figs}
</body></html>
"""


def write_results(out_dir: str | os.PathLike[str], rows: Sequence[dict[str, Any]], value_names: Sequence[str],
                  meta: dict[str, Any]) -> list[Path]:
    """Write ``results.csv``, ``results.json``, ``results.md`` and ``report.html`` into *out_dir*; return their paths.

    *rows* have the keys of :data:`RESULT_KEYS`; *meta* goes into ``results.json`` (its ``sweeps``,
    ``{name: values}``, selects the per-setting plots).
    """
    out = Path(out_dir)
    flat = flat_rows(rows, value_names)
    cols = columns(value_names)
    paths = [out / n for n in ("results.csv", "results.json", "results.md", "report.html")]
    with atomic_open(paths[0], "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in flat:
            w.writerow(["" if r[c] is None else (repr(r[c]) if isinstance(r[c], float) else r[c]) for c in cols])
    with atomic_open(paths[1], "w", encoding="utf-8") as fh:
        json.dump(dict(meta) | {"columns": cols, "rows": flat}, fh, indent=2, default=str)
        fh.write("\n")
    with atomic_open(paths[2], "w", encoding="utf-8") as fh:
        fh.write(markdown_table(flat, value_names))
    with atomic_open(paths[3], "w", encoding="utf-8") as fh:
        fh.write(_html(flat, value_names, meta))
    return paths

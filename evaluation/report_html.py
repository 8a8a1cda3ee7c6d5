"""The HTML page of an evaluation report (:mod:`evaluation.report`): one self-contained file, every figure inline
as a base64 PNG, the relation metric beside the published figures, every metric in a table."""

from __future__ import annotations

import base64
import html
from typing import Any, Sequence

__all__ = ["page"]


def _relations_html(rel: dict[str, Any] | None) -> str:
    """Side-by-side table: our relation metric per trajectory vs the published numbers (mean ± std)."""
    if not rel:
        return ""
    from .published import METRIC_KEYS

    units = {"trans": "m", "trans_sq": "m²", "rot": "deg", "rot_sq": "deg²"}
    pub = rel.get("published") or {}
    cols = [k for k in ("estimate", "odometry") if k in rel]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    head += "".join(f"<th>{n}</th>" for k, n in (("cartographer", "Cartographer"), ("graph_mapping", "Graph Mapping")) if k in pub)
    body = []
    for key, (label, m_attr, s_attr) in METRIC_KEYS.items():
        cells = []
        for c in cols:
            mv, sv = rel[c].get(m_attr), rel[c].get(s_attr)
            cells.append("<td>–</td>" if mv is None else f"<td>{mv:.4g} ± {sv:.4g}</td>")
        for meth in ("cartographer", "graph_mapping"):
            if meth in pub:
                cells.append(f"<td>{pub[meth][key]['mean']:g} ± {pub[meth][key]['std']:g}</td>")
        body.append(f"<tr><td>{html.escape(label)} [{units[key]}]</td>{''.join(cells)}</tr>")
    missing = ", ".join(f"{c}: {rel[c].get('n_missing')} of {rel[c].get('n_used', 0) + rel[c].get('n_missing', 0)}" for c in cols)
    return (f"<h2>Kümmerle relation metric ({html.escape(str(rel.get('dataset')))})</h2>"
            f"<table><tr><th>metric</th>{head}</tr>{''.join(body)}</table>"
            f"<p>Relations without a matching stamp (not used): {html.escape(missing)}.</p>")


def page(metrics: dict[str, Any], flat: dict[str, Any], figures: Sequence[Any], notes: Sequence[str]) -> str:
    """The report page: *metrics* (nested) and the same *flat* (``a.b.c`` keys), *figures* (title, png bytes,
    caption) and *notes*."""
    rows = "\n".join(
        f"<tr><td>{html.escape(k)}</td><td>{html.escape(v if isinstance(v, str) else f'{v:.6g}' if isinstance(v, float) else str(v))}</td></tr>"
        for k, v in flat.items()
    )
    figs = "\n".join(
        f'<figure><h2>{html.escape(f.title)}</h2><img alt="{html.escape(f.title)}" '
        f'src="data:image/png;base64,{base64.b64encode(f.png).decode("ascii")}"/>'
        f"<figcaption>{html.escape(f.caption)}</figcaption></figure>"
        for f in figures
    )
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    rel_table = _relations_html(metrics.get("relations"))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>gpslam report</title>
<style>
body {{ font-family: sans-serif; max-width: 1000px; margin: 2em auto; color: #222; }}
table {{ border-collapse: collapse; font-size: 0.9em; margin-bottom: 1em; }}
td, th {{ border-bottom: 1px solid #ddd; padding: 2px 12px 2px 2px; font-family: monospace; text-align: left; }}
figure {{ margin: 2em 0; }} img {{ max-width: 100%; }} figcaption {{ color: #555; }}
</style></head><body>
<h1>gpslam evaluation report</h1>
<p>Result folder: <code>{html.escape(str(metrics.get("result_dir", "")))}</code></p>
{f"<h2>Notes</h2><ul>{notes}</ul>" if notes else ""}
{rel_table}
<h2>All metrics</h2>
<table>
{rows}
</table>
{figs}
</body></html>
"""

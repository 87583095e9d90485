"""``report.html``: one self-contained page comparing runs (table, figures, interactive 3-D views).

The page opens offline: figures are embedded PNGs, and the 3-D views use plotly.js, whose bundle is inlined
from the ``plotly`` package (``plotly.offline.get_plotlyjs()``; ~4.8 MB, the largest part of the page). Meshes
travel once per example pair (target and source as base64 float32 vertices and int32 faces); each run adds
one colour index per source vertex (its map), so the page grows by ~25 kB per run and pair at 5k vertices.
Display meshes above :data:`MAX_DISPLAY_FACES` faces are rejected with a clear error rather than written:
the numbers are never computed from what is displayed.

Per example pair the page shows the target (coloured by its coordinates) and, for every run, the source
coloured through that run's map (vertex i gets the colour of its image), as :mod:`shapecorr.viz.render` does;
the views share their camera (rotating one rotates the others). One pair is shown at a time, chosen in a list:
browsers keep only ~16 WebGL contexts alive, one per view, so 4 pairs x (4 runs + target) at once would lose
some. The table sorts by a click on a header; published rows are a separate table.
"""

from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from shapecorr.errors import ConfigError
from shapecorr.eval import compare
from shapecorr.viz.compare import EXAMPLES_GRID_PNG, read_map
from shapecorr.viz.render import coordinate_colors

REPORT_HTML = "report.html"
#: Largest display mesh (faces) put into the page: ~20 MB for 4 runs x 4 pairs stays reachable below it.
MAX_DISPLAY_FACES = 60_000
#: Height in pixels of one 3-D view.
VIEW_HEIGHT = 360

_STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f2f2; cursor: pointer; }
td:first-child, th:first-child { text-align: left; }
td.best { font-weight: bold; background: #e6f4e6; }
table.published td { color: #555; font-style: italic; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.3em; }
.fig { display: inline-block; vertical-align: top; max-width: 32%; margin-right: 1%; }
.fig.wide { display: block; max-width: 100%; }
.views { display: flex; flex-wrap: wrap; }
.view { width: 250px; height: VIEW_HEIGHTpx; margin: 2px; border: 1px solid #ddd; }
.caption { font-size: 0.8em; text-align: center; }
""".replace("VIEW_HEIGHT", str(VIEW_HEIGHT))

_SCRIPT = r"""
function b64(s, Type) {
  const raw = atob(s), bytes = new Uint8Array(raw.length);
  for (let i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
  return new Type(bytes.buffer);
}
function sortTable(th) {
  const table = th.closest('table'), body = table.tBodies[0], col = th.cellIndex;
  const dir = th.dataset.dir === 'asc' ? -1 : 1;
  th.dataset.dir = dir === 1 ? 'asc' : 'desc';
  const rows = Array.from(body.rows);
  rows.sort((a, b) => {
    const x = a.cells[col].dataset.v, y = b.cells[col].dataset.v;
    const fx = parseFloat(x), fy = parseFloat(y);
    if (isNaN(fx) || isNaN(fy)) return dir * String(x).localeCompare(String(y));
    return dir * (fx - fy);
  });
  rows.forEach(r => body.appendChild(r));
}
function colorStrings(rgb) {
  const out = new Array(rgb.length / 3);
  for (let i = 0; i < out.length; i++) out[i] = `rgb(${rgb[3*i]},${rgb[3*i+1]},${rgb[3*i+2]})`;
  return out;
}
function mesh3d(verts, faces, colors) {
  const n = verts.length / 3, m = faces.length / 3;
  const x = new Float32Array(n), y = new Float32Array(n), z = new Float32Array(n);
  for (let i = 0; i < n; i++) { x[i] = verts[3*i]; y[i] = verts[3*i+1]; z[i] = verts[3*i+2]; }
  const I = new Int32Array(m), J = new Int32Array(m), K = new Int32Array(m);
  for (let f = 0; f < m; f++) { I[f] = faces[3*f]; J[f] = faces[3*f+1]; K[f] = faces[3*f+2]; }
  return {type: 'mesh3d', x: x, y: y, z: z, i: I, j: J, k: K, vertexcolor: colors, flatshading: false,
          lighting: {ambient: 0.55, diffuse: 0.6, specular: 0.05}, hoverinfo: 'skip'};
}
let viewData = null;
function showPair(p) {
  // one pair's views at a time: browsers keep only ~16 WebGL contexts alive, one per view
  const layoutBase = {margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: false,
    scene: {aspectmode: 'data', xaxis: {visible: false}, yaxis: {visible: false}, zaxis: {visible: false},
            camera: {up: {x: 0, y: 1, z: 0}, eye: {x: 0, y: 0.1, z: 2.4}}}};
  const config = {displaylogo: false, responsive: false};
  const pair = viewData.pairs[p];
  document.querySelectorAll('.view').forEach(d => { Plotly.purge(d); d.textContent = ''; });
  const tv = b64(pair.target.verts, Float32Array), tf = b64(pair.target.faces, Int32Array);
  const sv = b64(pair.source.verts, Float32Array), sf = b64(pair.source.faces, Int32Array);
  const tcol = b64(pair.target.colors, Uint8Array);
  const divs = [];
  const target = document.getElementById('view-target');
  Plotly.newPlot(target, [mesh3d(tv, tf, colorStrings(tcol))], JSON.parse(JSON.stringify(layoutBase)), config);
  divs.push(target);
  document.getElementById('caption-target').textContent = `target ${pair.target.name}`;
  pair.runs.forEach((run, r) => {
    const div = document.getElementById(`view-${r}`);
    document.getElementById(`caption-${r}`).textContent = `${run.name}: ${pair.source.name}`;
    if (run.map === null) { div.textContent = 'no map for this pair'; return; }
    const map = b64(run.map, Int32Array), rgb = new Uint8Array(3 * map.length);
    for (let i = 0; i < map.length; i++) for (let c = 0; c < 3; c++) rgb[3*i+c] = tcol[3*map[i]+c];
    Plotly.newPlot(div, [mesh3d(sv, sf, colorStrings(rgb))], JSON.parse(JSON.stringify(layoutBase)), config);
    divs.push(div);
  });
  let syncing = false;
  divs.forEach(src => src.on('plotly_relayout', ev => {
    if (syncing || !ev['scene.camera']) return;
    syncing = true;
    Promise.all(divs.filter(d => d !== src).map(d => Plotly.relayout(d, {'scene.camera': ev['scene.camera']})))
      .finally(() => { syncing = false; });
  }));
}
function buildViews() {
  viewData = JSON.parse(document.getElementById('mesh-data').textContent);
  const select = document.getElementById('pair-select');
  select.addEventListener('change', () => showPair(Number(select.value)));
  showPair(0);
}
document.addEventListener('DOMContentLoaded', () => {
  document.querySelectorAll('th').forEach(th => th.addEventListener('click', () => sortTable(th)));
  buildViews();
});
"""


def _plotly_bundle() -> str:
    """plotly.js from the ``plotly`` package, or a ConfigError saying how to get it."""
    try:
        from plotly.offline import get_plotlyjs
    except ImportError:
        raise ConfigError("report.html's 3-D views need the plotly package (pip install plotly); the other "
                          "comparison files are written") from None
    return get_plotlyjs()


def _b64(array: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def _mesh_entry(verts: np.ndarray, faces: np.ndarray, name: str) -> dict:
    if len(faces) > MAX_DISPLAY_FACES:
        raise ConfigError(f"shape {name} has {len(faces)} faces, more than the {MAX_DISPLAY_FACES} the report's "
                          "3-D views take: use fewer or smaller example pairs (n_examples=0 skips the views)")
    v = np.asarray(verts, np.float64)
    v = (v - (v.max(0) + v.min(0)) / 2) / max(float((v.max(0) - v.min(0)).max()), 1e-12)
    return {"name": name, "verts": _b64(v, np.float32), "faces": _b64(faces, np.int32)}


def mesh_data(runs: Sequence[compare.Run], examples: Sequence[tuple[str, str]],
              meshes: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> dict:
    """The JSON the page's viewers read: per example pair the two meshes, the target colours and each run's map."""
    out = []
    for x, y in examples:
        vy, fy = meshes[y]
        target = _mesh_entry(vy, fy, y)
        target["colors"] = _b64(np.round(255 * coordinate_colors(vy)), np.uint8)
        runs_out = []
        for run in runs:
            p2p = read_map(run, x, y)
            runs_out.append({"name": run.name, "map": None if p2p is None else _b64(p2p, np.int32)})
        out.append({"source": _mesh_entry(*meshes[x], x), "target": target, "runs": runs_out})
    return {"pairs": out}


def _table(runs: Sequence[compare.Run]) -> str:
    cols = compare.shown_columns(runs)
    best = compare.best_runs(runs)
    head = "<tr><th>run</th><th>pairs</th>" + "".join(f"<th>{html.escape(c.title)}</th>" for c in cols)
    head += "<th>device</th></tr>"
    rows = []
    for i, r in enumerate(runs):
        cells = [f'<td data-v="{html.escape(r.name)}">{html.escape(r.name)}</td>',
                 f'<td data-v="{r.values.get("n_pairs") or ""}">{r.values.get("n_pairs") or ""}</td>']
        for c in cols:
            v = r.values.get(c.key)
            cls = ' class="best"' if i in best.get(c.key, ()) else ""
            cells.append(f'<td{cls} data-v="{"" if v is None else v}">{compare.format_value(c, v)}</td>')
        device = html.escape(str(r.values.get("device", "")))
        cells.append(f'<td data-v="{device}">{device}</td>')
        rows.append('<tr class="run">' + "".join(cells) + "</tr>")
    return f'<table id="runs"><thead>{head}</thead><tbody>{"".join(rows)}</tbody></table>'


def _published_table(bench: str, rows) -> str:
    if not rows:
        return ""
    body = "".join(f"<tr><td>{html.escape(m)} (published)</td><td>{100 * v:.1f}</td><td>{html.escape(s)}</td></tr>"
                   for m, v, s in rows)
    return (f"<h3>Published on {html.escape(bench)} (papers' numbers on all test pairs; not measured here)</h3>"
            f'<table class="published"><thead><tr><th>method</th><th>mean error (x100)</th><th>source</th></tr>'
            f"</thead><tbody>{body}</tbody></table>")


def _image(path: Path, title: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    wide = " wide" if path.name == EXAMPLES_GRID_PNG else ""
    return (f'<div class="fig{wide}"><h3>{html.escape(title)}</h3>'
            f'<img alt="{html.escape(title)}" src="data:image/png;base64,{data}"></div>')


def _views(runs: Sequence[compare.Run], examples: Sequence[tuple[str, str]]) -> str:
    options = "".join(f'<option value="{p}">{html.escape(x)} &rarr; {html.escape(y)}</option>'
                      for p, (x, y) in enumerate(examples))
    cells = ['<div><div class="view" id="view-target"></div><div class="caption" id="caption-target"></div></div>']
    cells += [f'<div><div class="view" id="view-{r}"></div><div class="caption" id="caption-{r}"></div></div>'
              for r in range(len(runs))]
    return (f'<p>Example pair: <select id="pair-select">{options}</select></p>'
            f'<div class="views">{"".join(cells)}</div>')


def write_report_html(path: str | os.PathLike, runs: Sequence[compare.Run], figures: Mapping[str, Path],
                      examples: Sequence[tuple[str, str]], meshes: Mapping[str, tuple[np.ndarray, np.ndarray]],
                      note: str = "") -> Path:
    """Write ``report.html`` (see the module docstring); ``figures`` maps titles to PNG files to embed."""
    from shapecorr.eval.compare import published_rows, write_text

    view_runs = [r for r in runs if r.has_records]
    examples = list(examples) if meshes else []
    bench, published = published_rows(runs)
    dataset = ", ".join(sorted({Path(r.dataset).name for r in runs if r.dataset})) or "unknown data"
    body = [f"<h1>Comparison of {len(runs)} runs on {html.escape(dataset)}</h1>"]
    if note:
        body.append(f"<p>{html.escape(note)}</p>")
    body.append("<p>Errors: geodesic, x100 of sqrt(area of the target). Bold: best measured value per column. "
                "Click a header to sort.</p>")
    body.append(_table(runs))
    body.append(_published_table(bench, published))
    body += [_image(p, title) for title, p in figures.items()]
    if examples and view_runs:
        body.append("<h2>Example pairs (drag to rotate, scroll to zoom; the views move together)</h2>")
        body.append("<p>Target coloured by its coordinates; each run's source coloured through its map (vertex i "
                    "takes the colour of its image).</p>")
        body.append(_views(view_runs, examples))
        data = json.dumps(mesh_data(view_runs, examples, meshes)).replace("</", "<\\/")
        body.append(f'<script type="application/json" id="mesh-data">{data}</script>')
        scripts = f"<script>{_plotly_bundle()}</script><script>{_SCRIPT}</script>"
    else:
        scripts = f"<script>{_SCRIPT.replace('buildViews();', '')}</script>"
    page = ("<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>shapecorr comparison</title>"
            f"<style>{_STYLE}</style>{scripts}</head><body>{''.join(body)}</body></html>\n")
    return write_text(path, page)

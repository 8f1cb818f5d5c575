"""One-page HTML reports of a run and of a suite: self-contained files that work offline.

Every image is inlined as a data URI and the page's script and style come from
the package's ``web/`` folder, so a report is one file that fetches nothing.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
from importlib import resources
from pathlib import Path

from PIL import Image

from .camerascene import camera_scene
from .imageio_utils import atomic_write
from .metrics import DECIMALS, fixed
from .planners.base import planner_label
from .report import METRIC_LABELS

#: Name of a run's page in its folder, and of a suite's in its report folder.
REPORT_FILE = "report.html"

#: JPEG quality of photographs (views, predictions) inlined into a page: a 20-view run at 128x128 stays small.
JPEG_QUALITY = 88

_METRIC_COLUMNS = [("views", "views"), ("psnr", "PSNR (dB)"), ("psnr_fg", "foreground PSNR (dB)"), ("ssim", "SSIM"),
                   ("distance_error", "distance error (%)"),
                   ("floor_psnr", "background alone: PSNR (dB)"),
                   ("floor_psnr_fg", "background alone: foreground PSNR (dB)"), ("fit_psnr", "fit PSNR (dB)"),
                   ("eval_seconds", "evaluation (s)")]


def _asset(name: str) -> str:
    return resources.files("mitsuba_active").joinpath("web", name).read_text(encoding="utf-8")


def data_uri(path, photo: bool = True) -> str | None:
    """The image file ``path`` as a data URI (JPEG for ``photo``, else PNG as it is); None when it is missing."""
    path = Path(path)
    if not path.is_file():
        return None
    if not photo:
        return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")
    with Image.open(path) as img:
        buf = io.BytesIO()
        img.convert("RGB").save(buf, format="JPEG", quality=JPEG_QUALITY)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(uri: str | None, alt: str, **attrs) -> str:
    if uri is None:
        return f'<div class="missing">{html.escape(alt)}: not written</div>'
    extra = "".join(f' {k.replace("_", "-")}="{html.escape(str(v))}"' for k, v in attrs.items())
    return f'<img src="{uri}" alt="{html.escape(alt)}"{extra}>'


def _json_script(element_id: str, data) -> str:
    # "</" would end the script element early.
    text = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    return f'<script type="application/json" id="{element_id}">{text}</script>'


def _page(title: str, body: str, script: bool = False) -> str:
    js = f"<script>{_asset('report.js')}</script>" if script else ""
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{html.escape(title)}</title><style>{_asset('report.css')}</style></head>"
            f"<body>{body}{js}</body></html>\n")


def _metrics_table(metrics: list[dict]) -> str:
    if not metrics:
        return "<p>No evaluation yet.</p>"
    cols = [(k, label) for k, label in _METRIC_COLUMNS if any(m.get(k) is not None for m in metrics)]
    head = "".join(f"<th>{html.escape(label)}</th>" for _, label in cols)
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(str(fixed(m.get(k), DECIMALS.get(k, None))))}</td>"
                                    if m.get(k) is not None else "<td>n/a</td>" for k, _ in cols) + "</tr>"
                   for m in metrics)
    return f'<table class="metrics"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>'


def _plots(folder: Path) -> str:
    figures = [f'<figure>{_img(data_uri(folder / f"{m}.png", photo=False), label)}</figure>'
               for m, label in METRIC_LABELS.items() if (folder / f"{m}.png").is_file()]
    return f'<div class="plots">{"".join(figures)}</div>' if figures else ""


def run_page(run_dir, rec: dict) -> str:
    """The HTML of a run's report, from its folder and its record (run.json's content)."""
    run_dir = Path(run_dir)
    cfg = rec.get("config", {})
    planner = planner_label(cfg.get("planner", "?"))
    scene_name = rec.get("scene") or Path(str(cfg.get("scene", ""))).name
    captured = rec["captured"]
    files = rec.get("candidate_files")
    title = f"{scene_name}: {planner}, {len(captured)} view{'' if len(captured) == 1 else 's'}"
    facts = [("scene", scene_name), ("planner", planner), ("views", f"{len(captured)} of {cfg.get('budget', '?')}"),
             ("seed", cfg.get("seed")), ("resolution", cfg.get("resolution")),
             ("candidates", len(rec["candidates"])), ("held out", len(rec["heldout"])),
             ("planning (s)", rec.get("planning_seconds")), ("wall time (s)", rec.get("wall_seconds")),
             ("finished", "yes" if rec.get("finished") else "no")]
    versions = ", ".join(f"{k} {v}" for k, v in rec.get("versions", {}).items())
    facts_html = "".join(f"<dt>{html.escape(k)}</dt><dd>{html.escape(str(v))}</dd>" for k, v in facts
                         if v is not None)
    sheet = "".join(
        f'<figure>{_img(data_uri(run_dir / "views" / f"view_{n:03d}.png"), f"view {n}", id=f"view-{n}")}'
        f'<figcaption>#{n} {html.escape(Path(files[i]).stem if files else f"cand {i}")}</figcaption></figure>'
        for n, i in enumerate(captured))
    held = []
    for i in range(len(rec["heldout"])):
        stem = run_dir / "heldout" / f"heldout_{i:03d}"
        if not Path(f"{stem}_gt.png").is_file():
            continue
        cells = [(f"{stem}_pred.png", "prediction"), (f"{stem}_gt.png", "ground truth"),
                 (f"{stem}_variance.png", "variance")]
        held.append(f'<tr><th>{i}</th>' + "".join(
            f"<td>{_img(data_uri(p), f'{what} {i}')}</td>" for p, what in cells
            if what != "variance" or Path(p).is_file()) + "</tr>")
    held_html = (f'<table class="heldout"><thead><tr><th></th><th>prediction</th><th>ground truth</th>'
                 f'{"<th>variance (ensemble)</th>" if any("variance" in h for h in held) else ""}</tr></thead>'
                 f'<tbody>{"".join(held)}</tbody></table>' if held else
                 "<p>No held-out predictions yet (they are written when the run finishes).</p>")
    body = (f"<header><h1>{html.escape(title)}</h1><dl>{facts_html}</dl>"
            f'<p class="small">{html.escape(versions)}</p></header>'
            f'<section><h2>Cameras</h2><div id="camera-view" class="view3d">'
            f'<canvas width="760" height="520"></canvas><div class="controls"></div><div class="info"></div>'
            f"</div>{_json_script('camera-data', camera_scene(rec))}</section>"
            f"<section><h2>Held-out scores</h2>{_metrics_table(rec.get('metrics', []))}{_plots(run_dir)}</section>"
            f'<section><h2>Captured views</h2><div class="sheet">{sheet}</div></section>'
            f"<section><h2>Held-out views</h2>{held_html}</section>")
    return _page(title, body, script=True)


def write_run_page(run_dir, rec: dict) -> Path:
    """Write ``report.html`` into a run's folder (atomically); returns its path."""
    path = Path(run_dir) / REPORT_FILE
    text = run_page(run_dir, rec)
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def markdown_tables(text: str) -> str:
    """The report's Markdown (``## `` titles, paragraphs and pipe tables) as HTML."""
    out, rows = [], []

    def flush():
        if rows:
            head, *body = rows
            out.append("<table><thead><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in head) + "</tr></thead>"
                       "<tbody>" + "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>"
                                           for r in body) + "</tbody></table>")
            rows.clear()

    for line in text.splitlines():
        line = line.strip()
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if not all(set(c) <= set("-: ") for c in cells):  # not the row under the header
                rows.append(cells)
            continue
        flush()
        if line.startswith("#"):
            out.append(f"<h3>{html.escape(line.lstrip('#').strip())}</h3>")
        elif line:
            out.append(f"<p>{html.escape(line)}</p>")
    flush()
    return "".join(out)


def write_suite_page(folder, report_dir, title: str, tables: list[str], runs: dict) -> Path:
    """Write a suite's ``report.html`` into ``folder`` (its report folder being made, to become ``report_dir``).

    Args:
        tables: the report's Markdown tables.
        runs: scene -> planner -> run folders whose pages the suite's page links to.
    """
    folder, report_dir = Path(folder), Path(report_dir)
    plots = folder / "plots"
    sections = []
    for scene_dir in sorted(p for p in plots.iterdir() if p.is_dir()) if plots.is_dir() else []:
        sections.append(f"<h3>{html.escape(scene_dir.name)}</h3>{_plots(scene_dir)}")
    links = []
    for scene, by_planner in runs.items():
        items = []
        for planner, outs in by_planner.items():
            for out in outs:
                page = Path(out) / REPORT_FILE
                if page.is_file():
                    href = Path(os.path.relpath(page.resolve(), report_dir.resolve())).as_posix()
                    items.append(f'<li><a href="{html.escape(href)}">{html.escape(planner)}: '
                                 f"{html.escape(Path(out).name)}</a></li>")
        if items:
            links.append(f"<h3>{html.escape(scene)}</h3><ul>{''.join(items)}</ul>")
    body = (f"<header><h1>{html.escape(title)}</h1></header>"
            f"<section><h2>Tables</h2>{''.join(markdown_tables(t) for t in tables)}</section>"
            f"<section><h2>Plots</h2>{''.join(sections)}</section>"
            + (f"<section><h2>Runs</h2>{''.join(links)}</section>" if links else ""))
    path = folder / REPORT_FILE
    with atomic_write(path) as tmp:
        tmp.write_text(_page(title, body), encoding="utf-8")
    return path

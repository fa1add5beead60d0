"""The web UI at /: the dashboard built by `make web` (web/dist, or the copy an installed package
carries) with its /assets, else a server-rendered status page (jobs with live previews,
workers; no build step), which polls the REST API every two seconds.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

# The dashboard built by `make web`: package data renderfarm/web where an installed package
# carries it (the server image copies web/dist there before installing), else web/dist of this
# checkout; index_html() stands in for it when neither has been built.
_PACKAGED_WEB = Path(__file__).resolve().parents[1] / "web"
WEB_DIST = (
    _PACKAGED_WEB
    if (_PACKAGED_WEB / "index.html").is_file()
    else Path(__file__).resolve().parents[3] / "web" / "dist"
)

_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>renderfarm</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body { font: 14px system-ui, sans-serif; margin: 1.5rem; color: #222; }
h1 { font-size: 1.3rem; } table { border-collapse: collapse; }
td, th { padding: .3rem .7rem; border-bottom: 1px solid #ddd; text-align: left; }
.jobs { display: flex; flex-wrap: wrap; gap: 1rem; }
.job { border: 1px solid #ccc; border-radius: 6px; padding: .6rem; width: 280px; }
.job img { width: 256px; height: auto; image-rendering: pixelated; background: #000; }
progress { width: 256px; } code { font-size: 12px; }
</style></head><body>
<h1>renderfarm</h1>
<p>API: <a href="/docs">/docs</a> &middot; <a href="/metrics">/metrics</a></p>
<h2>Workers</h2><table id="workers"><tr><th>id</th><th>cores</th><th>tasks</th>
<th>samples/s</th></tr></table>
<h2>Jobs</h2><div class="jobs" id="jobs"></div>
<script>
function esc(s) { const d = document.createElement('div'); d.textContent = s; return d.innerHTML; }
async function refresh() {
  try {
    const w = await (await fetch('/api/v1/workers')).json();
    document.getElementById('workers').innerHTML =
      '<tr><th>id</th><th>cores</th><th>tasks</th><th>samples/s</th></tr>' +
      w.map(x => `<tr><td>${esc(x.id)}</td><td>${x.cores}</td><td>${x.tasks_in_flight}</td>` +
                 `<td>${Math.round(x.samples_per_s).toLocaleString()}</td></tr>`).join('');
    const j = (await (await fetch('/api/v1/jobs?page_size=24')).json()).jobs;
    document.getElementById('jobs').innerHTML = j.map(x => {
      const p = x.progress, err = p.error == null ? '-' : (100 * p.error).toFixed(2) + '%';
      const img = `/api/v1/jobs/${x.id}/image.png?v=${p.samples_merged}`;
      return `<div class="job"><b>${esc(x.name)}</b> <code>${x.id}</code><br>` +
        `<a href="/api/v1/jobs/${x.id}/image.exr"><img src="${img}" alt="preview"></a><br>` +
        `<progress max="${p.tiles_total}" value="${p.tiles_done}"></progress><br>` +
        `${x.state} &middot; ${p.mean_spp.toFixed(1)} spp &middot; error ${err}</div>`;
    }).join('');
  } catch (e) { /* server restarting: try again next round */ }
}
refresh(); setInterval(refresh, 2000);
</script></body></html>
"""


def index_html() -> str:
    return _PAGE


def add_dashboard(app: FastAPI) -> None:
    """GET / and /assets."""

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def index() -> Response:
        built = WEB_DIST / "index.html"
        if built.is_file():
            return FileResponse(built, headers={"Cache-Control": "no-cache"})
        return HTMLResponse(index_html())

    app.mount("/assets", _DashboardAssets(directory=WEB_DIST / "assets"), name="dashboard-assets")


class _DashboardAssets(StaticFiles):
    """web/dist/assets, or 404 for everything under /assets while the dashboard is not built
    (StaticFiles itself fails with a 500 then); checked per request, so `make web` on a running
    server is picked up."""

    def __init__(self, directory: Path):
        super().__init__(directory=directory, check_dir=False)

    async def check_config(self) -> None:
        if not Path(str(self.directory)).is_dir():
            raise StarletteHTTPException(404, "the dashboard is not built (make web)")
        await super().check_config()

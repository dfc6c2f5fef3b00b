"""The dashboard's routes: a static page, a JSON API it polls, the rig's buttons, the reports.

Who may do what: on a loopback address anyone on this machine may, but the Host header must name
loopback too (a page elsewhere cannot rebind its name to 127.0.0.1 and drive the rig). On any
other address a token is required (`serve --token` or STATION_TOKEN), as `Authorization: Bearer` or as the
`station_token` cookie the page sets from its `#token=` fragment. Every route that reads scans or
moves hardware checks it, and buttons refuse a request sent from another origin.
"""

from __future__ import annotations

import hmac
import ipaddress
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import AsyncIterator

from fastapi import Depends, FastAPI, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict

from station.errors import BadInputError, ScanFolderError, StationError
from station.serve.preview import raw_preview_jpeg
from station.serve.rig_control import RunnerStateError, ScanRequest, ScanRunner
from station.serve.scans import ScanCatalog, UnknownScanError

STATIC = Path(__file__).parent / "static"
TOKEN_COOKIE = "station_token"
MIN_TOKEN_LENGTH = 16
SHUTDOWN_WAIT_S = 30.0
# A scan folder's report is untrusted HTML: it runs in a sandbox with no scripts and no network.
REPORT_POLICY = "sandbox; default-src 'none'; img-src data:; style-src 'unsafe-inline'; font-src data:"


@dataclass(frozen=True)
class ServeConfig:
    host: str = "127.0.0.1"
    token: str | None = None
    elevations: int = 6  # the start form's defaults
    azimuths: int = 40
    poll_seconds: float = 1.0


class StartBody(BaseModel):
    """The start form. Unknown fields are refused rather than ignored (a typo must not pass)."""

    model_config = ConfigDict(extra="forbid")
    name: str
    elevations: int
    azimuths: int
    stone: str | None = None


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_exposure(host: str, token: str | None) -> None:
    """Only loopback goes without a token: whoever reaches the port could read scans and move the rig."""
    if token is not None and len(token) < MIN_TOKEN_LENGTH:
        raise BadInputError(f"--token (STATION_TOKEN) is too short: use at least {MIN_TOKEN_LENGTH} random characters")
    if token is None and not is_loopback(host):
        raise BadInputError(
            f"serve --host {host}: only a loopback address may be served without a token; give --token or set STATION_TOKEN"
        )


def create_app(runner: ScanRunner, catalog: ScanCatalog, config: ServeConfig) -> FastAPI:
    check_exposure(config.host, config.token)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        # Shutting down mid-scan: stop at a frame boundary so the folder is left resumable.
        try:
            runner.cancel()
        except RunnerStateError:
            return
        runner.wait(SHUTDOWN_WAIT_S)

    app = FastAPI(title="station dashboard", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    guard = Depends(_guard(config))

    @app.exception_handler(StationError)
    def station_error(request: Request, exc: StationError) -> JSONResponse:
        return JSONResponse({"error": str(exc)}, status_code=_status_for(exc))

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    @app.get("/api/state", dependencies=[guard])
    def state() -> dict:
        return {
            **runner.snapshot(),
            "defaults": {"elevations": config.elevations, "azimuths": config.azimuths},
            "poll_seconds": config.poll_seconds,
        }

    @app.get("/api/queue", dependencies=[guard])
    def queue() -> dict:
        queue_file = None if catalog.queue is None else str(catalog.queue)
        return {"queue": queue_file, "queue_exists": catalog.queue_exists(), "scans": catalog.rows()}

    @app.get("/api/scan/preview.jpg", dependencies=[guard])
    def preview() -> Response:
        latest = runner.latest_frame()
        if latest is None:
            raise UnknownScanError("no frame has been shot yet")
        folder, relative = latest
        path = (folder / relative).resolve()
        return Response(raw_preview_jpeg(path), media_type="image/jpeg", headers={"Cache-Control": "no-store"})

    @app.post("/api/scan/start", dependencies=[guard])
    def start(body: StartBody) -> dict:
        runner.start(ScanRequest(body.name, body.elevations, body.azimuths, body.stone or None))
        return runner.snapshot()

    @app.post("/api/scan/pause", dependencies=[guard])
    def pause() -> dict:
        runner.pause()
        return runner.snapshot()

    @app.post("/api/scan/resume", dependencies=[guard])
    def resume() -> dict:
        runner.resume()
        return runner.snapshot()

    @app.post("/api/scan/cancel", dependencies=[guard])
    def cancel() -> dict:
        runner.cancel()
        return runner.snapshot()

    @app.post("/api/operator/done", dependencies=[guard])
    def operator_done() -> dict:
        runner.confirm_operator()
        return runner.snapshot()

    @app.get("/scans/{key}/report", dependencies=[guard])
    def report(key: str) -> FileResponse:
        return FileResponse(
            catalog.report(key), media_type="text/html",
            headers={"Content-Security-Policy": REPORT_POLICY, "Cache-Control": "no-cache"},
        )

    return app


def _status_for(exc: StationError) -> int:
    if isinstance(exc, UnknownScanError):
        return 404
    if isinstance(exc, ScanFolderError):
        return 403  # a path that escapes its scan folder
    if isinstance(exc, RunnerStateError):
        return 409
    if isinstance(exc, BadInputError):
        return 400
    return 500


def _guard(config: ServeConfig):
    """The check in front of every route that reads scans or moves hardware."""

    def guard(request: Request) -> None:
        if config.token is None:
            if not is_loopback(request.url.hostname or ""):
                raise HTTPException(403, "this dashboard answers only to a loopback host name")
        else:
            offered = _offered_token(request)
            if offered is None or not hmac.compare_digest(offered.encode("utf-8"), config.token.encode("utf-8")):
                raise HTTPException(401, "token missing or wrong: open the dashboard as http://HOST:PORT/#token=...")
        if request.method != "GET":
            _refuse_cross_site(request)

    return guard


def _refuse_cross_site(request: Request) -> None:
    """A button press must come from this page: a foreign Origin is refused, and without an Origin only a
    JSON body is taken, which a cross-site form cannot send and a cross-site script cannot without a
    CORS preflight this server never grants."""
    origin = request.headers.get("origin")
    if origin is not None and origin != f"{request.url.scheme}://{request.url.netloc}":
        raise HTTPException(403, f"refused a request from another origin ({origin})")
    if origin is None and not request.headers.get("content-type", "").startswith("application/json"):
        raise HTTPException(403, "refused a request with neither this page's Origin nor a JSON body")


def _offered_token(request: Request) -> str | None:
    scheme, _, value = request.headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer" and value:
        return value.strip()
    return request.cookies.get(TOKEN_COOKIE)

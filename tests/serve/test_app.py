"""``hdrcap serve``: the API and its JSON, the event streams, the pages, and every safety rule (an
attack that must fail next to a request that must succeed), against run folders the simulated
camera wrote (complete, failed, stopped, killed) and an archive ``hdrcap batch`` wrote."""

from __future__ import annotations

import http.client
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import tracemalloc
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")

from starlette.testclient import TestClient  # noqa: E402

from hdrcap.acquire.capture.manifest import EventLog, Manifest  # noqa: E402
from hdrcap.pipeline.errors import InputError  # noqa: E402
from hdrcap.serve import create_app  # noqa: E402
from hdrcap.serve.events import tail_offset  # noqa: E402
from hdrcap.serve.safety import check_bind, is_loopback  # noqa: E402
from tests.helpers.jobs import mock_job  # noqa: E402

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
BASE = "http://127.0.0.1:8765"
TOKEN = "s3cret-token-0123456789"
PNG = b"\x89PNG\r\n\x1a\n"


#: Keys and types of an entry of GET /api/runs.
RUN_KEYS = {
    "name": str,
    "state": str,
    "started": (str, type(None)),
    "updated": (str, type(None)),
    "frames_done": int,
    "frames_planned": (int, type(None)),
    "exit_code": (int, type(None)),
    "message": (str, type(None)),
    "job": (str, type(None)),
    "camera": (str, type(None)),
    "target_snr_db": (float, int, type(None)),
    "predicted_snr_db": (float, int, type(None)),
    "achieved_snr_db": (float, type(None)),
    "eta_s": (float, int, type(None)),
}
DETAIL_KEYS = set(RUN_KEYS) | {
    "last_event",
    "outputs",
    "plan",
    "calibration",
    "camera_record",
    "figures",
    "completion",
    "links",
}


def _hdrcap(*args, env=None, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "hdrcap", *map(str, args)],
        cwd=cwd or REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, **(env or {})},
    )


def _job(tmp: Path, name: str, folder: Path, seed: int = 1, faults: str = "") -> Path:
    return mock_job(tmp / f"{name}.toml", name=name, size="48x32", seed=seed, camera=faults, folder=folder)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """ROOT with two complete runs (``hdrcap capture`` and ``hdrcap run``), a failed run (card
    full, exit 4), a stopped run (SIGTERM, exit 143) and a killed run (no stop event); their
    archive from ``hdrcap batch`` (the two complete runs)."""
    tmp = tmp_path_factory.mktemp("serve")
    root = tmp / "runs"
    root.mkdir()
    env = {"HDRCAP_LOCK_DIR": str(tmp / "locks")}
    saved = os.environ.get("HDRCAP_LOCK_DIR")
    os.environ["HDRCAP_LOCK_DIR"] = str(tmp / "locks")  # this process's view of the locks too
    cap = _hdrcap(
        "capture", "--camera", "mock:camera-B", "--size", "48x32", "--times", "0.004", "0.064", "0.5",
        "--run-dir", root / "cap", "--seed", "3", "--no-progress", env=env,
    )  # fmt: skip
    assert cap.returncode == 0, cap.stderr
    done = _hdrcap("run", _job(tmp, "lab", root / "lab"), "--no-progress", env=env)
    assert done.returncode == 0, done.stderr
    failed = _hdrcap("run", _job(tmp, "full", root / "full", faults="faults = { card_full_after = 2 }"), env=env)
    assert failed.returncode == 4, failed.stderr
    killed = _hdrcap("run", _job(tmp, "killed", root / "killed", faults="faults = { kill_after = 2 }"), env=env)
    assert killed.returncode == 137, killed.stderr
    _stopped_run(tmp, root / "stopped")
    archive = tmp / "lab.zarr"
    batch = _hdrcap(
        "batch", root / "cap", root / "lab", "--camera", "camera-B", "-o", archive, "--workers", "1", env=env
    )
    assert batch.returncode == 0, batch.stderr
    (tmp / "outside").mkdir()
    (tmp / "outside" / "secret.txt").write_text("not for the web")
    yield {"tmp": tmp, "root": root, "archive": archive}
    if saved is None:
        os.environ.pop("HDRCAP_LOCK_DIR", None)
    else:
        os.environ["HDRCAP_LOCK_DIR"] = saved


def _stopped_run(tmp: Path, folder: Path) -> None:
    """A run ended by SIGTERM before its first frame (as ``systemctl stop`` would)."""
    from hdrcap.acquire.camera.mock import MockCamera
    from hdrcap.acquire.capture.job import load_job
    from hdrcap.acquire.capture.run import run_job
    from hdrcap.acquire.capture.session import RunInterrupted, StopEvent
    from hdrcap.mock_camera.scenes import make_scene

    stop = StopEvent()
    stop.stop(signal.SIGTERM)
    job = load_job(_job(tmp, "stopped", folder))
    cam = MockCamera("camera-B", make_scene("hdr", (32, 48), decades=3.0, x_max=2e4), seed=2)
    with pytest.raises(RunInterrupted):
        run_job(job, progress=False, echo=lambda _s: None, camera=cam, stop=stop)


@pytest.fixture(scope="module")
def client(site):
    app = create_app(site["root"], [site["archive"]])
    with TestClient(app, base_url=BASE) as c:
        yield c


def _snapshot(folder: Path) -> dict:
    """Every path below ``folder`` with its size and modification time."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for n in dirnames + filenames:
            p = Path(dirpath) / n
            st = p.lstat()
            out[str(p)] = (st.st_size, st.st_mtime_ns)
    return out


def _check_types(entry: dict, keys: dict) -> None:
    for key, kind in keys.items():
        assert isinstance(entry[key], kind), (key, entry[key])


def _sse(text: str) -> list[tuple[str | None, str | None, dict]]:
    """(id, event, data) of each message of a server-sent event stream."""
    out = []
    for block in text.split("\n\n"):
        fields: dict[str, str] = {}
        for line in block.splitlines():
            if line.startswith(":") or ":" not in line:
                continue
            k, v = line.split(":", 1)
            fields[k] = v[1:] if v.startswith(" ") else v
        if "data" in fields:
            out.append((fields.get("id"), fields.get("event"), json.loads(fields["data"])))
    return out


# --------------------------------------------------------------------------- the runs list
def test_runs_lists_each_run_with_its_state(client, site):
    res = client.get("/api/runs")
    assert res.status_code == 200 and res.headers["content-type"] == "application/json"
    runs = res.json()
    assert res.headers["x-total-count"] == "5"
    by = {r["name"]: r for r in runs}
    assert set(by) == {"cap", "lab", "full", "killed", "stopped"}
    for r in runs:
        assert set(r) == set(RUN_KEYS)
        _check_types(r, RUN_KEYS)
    for name in ("cap", "lab"):
        assert by[name]["state"] == "complete" and by[name]["frames_done"] == by[name]["frames_planned"] == 6
        assert by[name]["achieved_snr_db"] > 10 and by[name]["exit_code"] is None
    assert by["full"]["state"] == "failed" and by["full"]["exit_code"] == 4 and "full" in by["full"]["message"].lower()
    assert by["full"]["frames_done"] < by["full"]["frames_planned"]
    assert by["stopped"]["state"] == "stopped" and by["stopped"]["exit_code"] == 143
    assert "signal 15" in by["stopped"]["message"]
    assert by["killed"]["state"] == "failed" and by["killed"]["exit_code"] is None
    assert "without a stop event" in by["killed"]["message"]
    assert by["lab"]["job"] == "lab" and by["lab"]["camera"].startswith("Simulated camera-B")
    starts = [r["started"] for r in runs]
    assert starts == sorted(starts, reverse=True)  # newest first


def test_runs_are_paged(client):
    res = client.get("/api/runs?limit=2&offset=1")
    assert len(res.json()) == 2 and res.headers["x-total-count"] == "5"
    assert res.headers["link"] == '</api/runs?limit=2&offset=3>; rel="next"'
    assert [r["name"] for r in res.json()] == [r["name"] for r in client.get("/api/runs").json()[1:3]]
    assert "link" not in client.get("/api/runs?limit=2&offset=3").headers
    for bad in ("limit=0", "limit=5000", "offset=-1", "limit=x"):
        res = client.get(f"/api/runs?{bad}")
        assert res.status_code == 400 and "error" in res.json(), bad


# --------------------------------------------------------------------------- one run
def test_run_detail(client, site):
    res = client.get("/api/runs/lab")
    assert res.status_code == 200
    d = res.json()
    assert set(d) == DETAIL_KEYS
    _check_types(d, RUN_KEYS)
    assert d["outputs"] == {"exr": "hdr.exr", "png": "preview.png"}
    plan = d["plan"]
    assert plan["frames"] == 6 and plan["dark_strategy"] == "matched"
    planned = Manifest(site["root"] / "lab").header()["plan"]["frames"]
    assert [e["exposure_s"] for e in plan["exposures"]] == sorted({f["exposure_s"] for f in planned})
    assert [e["exposure_s"] for e in plan["exposures"]] == pytest.approx([0.004, 1 / 15, 0.5])  # camera-B's times
    assert all(
        e["dark_strategy"] == "matched" and e["light_frames"] == 1 and e["dark_frames"] == 1 for e in plan["exposures"]
    )
    assert d["figures"]["shape"] == [32, 48] and d["figures"]["finite"] is True
    assert d["achieved_snr_db"] == pytest.approx(20 * math.log10(1 / d["figures"]["median_relative_sigma"]))
    assert d["completion"]["status"] == "done" and d["last_event"]["event"] == "done"
    assert set(d["links"]) == {"preview", "snr", "sigma", "quality", "events", "files"}
    # a failed run: no outputs, so no images
    full = client.get("/api/runs/full").json()
    assert full["outputs"] == {"exr": None, "png": None} and set(full["links"]) == {"events", "files"}
    assert full["last_event"]["event"] == "stop" and full["figures"] is None
    assert client.get("/api/runs/nosuchrun").status_code == 404


def test_images_are_pngs_from_the_run_or_drawn_from_its_exr(client, site):
    for kind in ("preview", "snr", "sigma", "quality"):
        res = client.get(f"/api/runs/lab/{kind}.png")
        assert res.status_code == 200 and res.headers["content-type"] == "image/png", kind
        assert res.content.startswith(PNG)
    assert client.get("/api/runs/lab/preview.png").content == (site["root"] / "lab" / "preview.png").read_bytes()
    # a run folder without preview.png: the preview is drawn from the EXR
    copy = site["root"] / "nopng"
    shutil.copytree(site["root"] / "cap", copy, ignore=shutil.ignore_patterns("preview.png", ".*"))
    try:
        res = client.get("/api/runs/nopng/preview.png")
        assert res.status_code == 200 and res.content.startswith(PNG)
        assert res.content != (site["root"] / "cap" / "preview.png").read_bytes() or True
    finally:
        shutil.rmtree(copy)
    assert client.get("/api/runs/lab/other.png").status_code == 404
    assert client.get("/api/runs/full/snr.png").status_code == 404


def test_files_are_listed_a_page_at_a_time_and_sent(client, site):
    top = client.get("/api/runs/lab/files").json()
    assert set(top) == {"folder", "offset", "limit", "total", "next_offset", "files"}
    names = [f["name"] for f in top["files"]]
    assert names == sorted(names) and {"frames", "manifest.jsonl", "events.jsonl", "hdr.exr"} <= set(names)
    assert not any(n.startswith(".") for n in names)  # the lock file is not shown
    frames = sorted(p.name for p in (site["root"] / "lab" / "frames").iterdir())
    page = client.get("/api/runs/lab/files?folder=frames&limit=4&offset=0").json()
    assert [f["name"] for f in page["files"]] == frames[:4] and page["total"] == 6 and page["next_offset"] == 4
    rest = client.get("/api/runs/lab/files?folder=frames&limit=4&offset=4").json()
    assert [f["name"] for f in rest["files"]] == frames[4:] and rest["next_offset"] is None
    f = page["files"][0]
    assert f["kind"] == "file" and f["bytes"] == (site["root"] / "lab" / f["path"]).stat().st_size
    # a frame is a download; the manifest is text
    res = client.get(f"/api/runs/lab/files/{f['path']}")
    assert res.status_code == 200 and res.content == (site["root"] / "lab" / f["path"]).read_bytes()
    assert (
        res.headers["content-type"] == "application/octet-stream" and "attachment" in res.headers["content-disposition"]
    )
    res = client.get("/api/runs/lab/files/manifest.jsonl")
    assert (
        res.headers["content-type"].startswith("text/plain")
        and res.text == (site["root"] / "lab" / "manifest.jsonl").read_text()
    )


# --------------------------------------------------------------------------- event streams
def test_events_of_a_finished_run_then_the_end(client, site):
    with client.stream("GET", "/api/runs/full/events") as res:
        assert res.status_code == 200 and res.headers["content-type"].startswith("text/event-stream")
        text = "".join(res.iter_text())
    msgs = _sse(text)
    events = [m for m in msgs if m[1] == "event"]
    assert [e[2] for e in events] == EventLog(site["root"] / "full").events()
    ids = [int(e[0]) for e in events]
    assert ids == sorted(ids) and ids[-1] == (site["root"] / "full" / "events.jsonl").stat().st_size
    assert msgs[-1][1] == "end" and msgs[-1][2]["state"] == "failed" and msgs[-1][2]["exit_code"] == 4
    # a browser that reconnects continues after the last id it saw; ?tail=N starts N events from the end
    with client.stream("GET", "/api/runs/full/events", headers={"Last-Event-ID": events[1][0]}) as res:
        again = [m for m in _sse("".join(res.iter_text())) if m[1] == "event"]
    assert [m[2] for m in again] == [e[2] for e in events[2:]]
    with client.stream("GET", "/api/runs/full/events?tail=2") as res:
        tail = [m for m in _sse("".join(res.iter_text())) if m[1] == "event"]
    assert [m[2] for m in tail] == [e[2] for e in events[-2:]]
    assert client.get("/api/runs/full/events", headers={"Last-Event-ID": "x"}).status_code == 400


def test_events_stream_follows_a_running_run(client, site):
    """Existing events first, then one appended while the stream is open; the stream ends once
    the run's lock is released (the run is over)."""
    from filelock import FileLock

    live = site["root"] / "live"
    live.mkdir()
    Manifest(live).append(Manifest(site["root"] / "lab").header())  # the plan only: nothing captured yet
    log = EventLog(live)
    log.emit("start", frames=6)
    log.emit("frame", key="k0", index=0, done=1, total=6, eta_s=1.0, temperature_c=None)
    lock = FileLock(str(live / ".hdrcap.lock"))
    lock.acquire()
    got: list = []
    try:
        assert client.get("/api/runs/live").json()["state"] == "running"
        with client.stream("GET", "/api/runs/live/events") as res:
            watchdog = threading.Timer(60, res.close)
            watchdog.start()
            buf = ""
            for chunk in res.iter_text():
                buf += chunk
                got = _sse(buf)
                kinds = [m[2].get("event") for m in got if m[1] == "event"]
                if kinds == ["start", "frame"]:
                    log.emit("frame", key="k1", index=1, done=2, total=6, eta_s=0.5, temperature_c=None)
                if kinds == ["start", "frame", "frame"]:
                    log.emit("stop", reason="test: stopped by signal 15", exit_code=143)
                    lock.release()
                if any(m[1] == "end" for m in got):
                    break
            watchdog.cancel()
    finally:
        lock.release()
        shutil.rmtree(live)
    events = [m[2] for m in got if m[1] == "event"]
    assert [e["event"] for e in events] == ["start", "frame", "frame", "stop"]
    assert events[2]["key"] == "k1" and got[-1][1] == "end" and got[-1][2]["state"] == "stopped"


def test_runs_stream_shows_a_new_run_within_seconds(site):
    """A run started while the page is open appears in the runs stream (and in /api/runs)."""
    app = create_app(site["root"])
    with live_server(app) as (host, port):
        conn = http.client.HTTPConnection(host, port, timeout=60)
        conn.request("GET", "/api/stream")
        res = conn.getresponse()
        assert res.status == 200 and res.getheader("content-type").startswith("text/event-stream")
        first = _read_sse_until(res, lambda msgs: any(m[1] == "runs" for m in msgs))
        assert {r["name"] for r in first[-1][2]["runs"]} >= {"cap", "lab"}
        t0 = time.monotonic()
        env = {"HDRCAP_LOCK_DIR": os.environ["HDRCAP_LOCK_DIR"]}
        proc = subprocess.Popen(
            [sys.executable, "-m", "hdrcap", "run", str(_job(site["tmp"], "new", site["root"] / "new")), "--no-progress"],
            env={**os.environ, **env}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            msgs = _read_sse_until(
                res, lambda msgs: any(m[1] == "runs" and "new" in {r["name"] for r in m[2]["runs"]} for m in msgs)
            )
            seen = time.monotonic() - t0
        finally:
            assert proc.wait(120) == 0
            conn.close()
        new = next(r for r in msgs[-1][2]["runs"] if r["name"] == "new")
        assert new["state"] in ("running", "complete", "failed")  # seen while or just after it ran
        assert seen < 60
        with TestClient(app, base_url=BASE) as c:
            assert next(r for r in c.get("/api/runs").json() if r["name"] == "new")["state"] == "complete"
    shutil.rmtree(site["root"] / "new")


def _read_sse_until(res, done, timeout_s: float = 60.0) -> list:
    buf, deadline = b"", time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = res.fp.readline()
        if not line:
            break
        buf += line
        msgs = _sse(buf.decode())
        if done(msgs):
            return msgs
    raise AssertionError(f"not seen within {timeout_s} s: {buf[-500:]!r}")


@contextmanager
def live_server(app):
    """The app on a real uvicorn server on 127.0.0.1 (a free port), in a thread."""
    import uvicorn

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="error", lifespan="off", timeout_graceful_shutdown=1))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        yield "127.0.0.1", port
    finally:
        server.should_exit = True
        thread.join(15)
        sock.close()


# --------------------------------------------------------------------------- archives
def test_archive_series_of_a_region_with_sigma(client, site):
    import xarray as xr

    res = client.get("/api/archive/series?y=10&x=10&size=4")
    assert res.status_code == 200
    s = res.json()
    assert set(s) == {
        "archive",
        "y",
        "x",
        "size",
        "unit",
        "time",
        "run",
        "folder",
        "irradiance",
        "sigma",
        "n",
        "sigma_of_mean",
    }
    assert len(s["time"]) == len(s["irradiance"]) == len(s["sigma"]) == len(s["n"]) == 2
    assert all(v is not None and v > 0 for v in s["sigma"]) and sorted(s["folder"]) == ["cap", "lab"]
    assert "sqrt(sum sigma_i^2) / n" in s["sigma_of_mean"] and "independent" in s["sigma_of_mean"]
    ds = xr.open_zarr(site["archive"]).sortby("start_time")
    for k in range(2):
        reg = {
            v: ds[v].isel(run=k, y=slice(10, 14), x=slice(10, 14)).values.astype(np.float64)
            for v in ("irradiance", "sigma", "nexp", "quality")
        }
        ok = (reg["nexp"] > 0) & (reg["quality"] == 0)
        assert s["n"][k] == ok.sum() and 0 < s["n"][k] <= 16
        assert s["irradiance"][k] == pytest.approx(reg["irradiance"][ok].mean(), rel=1e-9)
        assert s["sigma"][k] == pytest.approx(np.sqrt((reg["sigma"][ok] ** 2).sum()) / ok.sum(), rel=1e-9)
        assert s["time"][k].startswith(str(ds["start_time"].values[k])[:19])
    assert s["time"] == sorted(s["time"])
    same = client.get("/api/archive/series?y=10&x=10&size=4&archive=lab").json()
    assert same == s


def test_archive_errors_and_preview(client):
    assert client.get("/api/archive/series?y=30&x=10&size=4").status_code == 400  # past the 32 rows
    assert client.get("/api/archive/series?x=10").status_code == 400
    assert client.get("/api/archive/series?y=1&x=1&size=0").status_code == 400
    assert client.get("/api/archive/series?y=1&x=1&archive=nope").status_code == 404
    res = client.get("/api/archive/preview.png")
    assert res.status_code == 200 and res.content.startswith(PNG)
    assert client.get("/api/archive/preview.png?run=7").status_code == 404
    (a,) = client.get("/api/archives").json()
    assert a["name"] == "lab" and a["runs"] == 2 and a["shape"] == [32, 48] and a["failed_runs"] == 0
    assert a["unit"] and a["first"] <= a["last"]


# --------------------------------------------------------------------------- pages
def test_pages_render(client):
    home = client.get("/")
    assert home.status_code == 200 and home.headers["content-type"].startswith("text/html")
    for name in ("cap", "lab", "full", "stopped", "killed"):
        assert f'href="/runs/{name}"' in home.text
    run = client.get("/runs/lab").text
    assert "/api/runs/lab/snr.png" in run and "matched" in run and "hdr.exr" in run
    assert "<script" in run and 'src="/static/app.js"' in run and "http" not in run.split("<body")[1].replace(BASE, "")
    assert client.get("/archives/lab").status_code == 200
    assert client.get("/runs/nosuchrun").status_code == 404
    assert client.get("/static/app.js").headers["content-type"].startswith("text/javascript")


# --------------------------------------------------------------------------- safety
TRAVERSALS = [
    "/api/runs/%2e%2e",  # encoded ..
    "/api/runs/%2E%2E/files/secret.txt",
    "/api/runs/lab/files/%2e%2e/%2e%2e/outside/secret.txt",
    "/api/runs/lab/files/..%2f..%2f..%2foutside%2fsecret.txt",  # encoded slashes
    "/api/runs/%252e%252e/files/outside/secret.txt",  # double-encoded
    "/api/runs/lab/files/%2Fetc%2Fpasswd",  # absolute path, encoded
    "/api/runs/lab/files//etc/passwd",  # absolute path
    "/api/runs/lab/files/..%5c..%5coutside%5csecret.txt",  # backslashes
    "/api/runs/lab/files/.hdrcap.lock",  # hidden files
    "/api/runs/lab/files/frames/%00",
    "/api/runs/lab/files?folder=..",
    "/api/runs/lab/files?folder=%2Fetc",
    "/api/runs/lab/files?folder=frames/../..",
]


@pytest.mark.parametrize("url", TRAVERSALS)
def test_traversal_is_refused(client, url):
    res = client.get(url)
    assert res.status_code in (403, 404), res.text
    assert "not for the web" not in res.text and "root:" not in res.text


def test_traversal_on_the_wire_is_refused(site):
    """Raw request lines (no client normalises them) against a real server."""
    with live_server(create_app(site["root"])) as (host, port):
        for path in ("/api/runs/../../outside/secret.txt", "/api/runs/lab/files/../../../outside/secret.txt",
                     "/api/runs/lab/files/%2e%2e/%2e%2e/outside/secret.txt", "/api/runs/..%2f..%2foutside/files/secret.txt"):  # fmt: skip
            conn = http.client.HTTPConnection(host, port, timeout=30)
            conn.putrequest("GET", path, skip_accept_encoding=True)
            conn.endheaders()
            res = conn.getresponse()
            body = res.read()
            assert res.status in (400, 403, 404) and b"not for the web" not in body, path
            conn.close()
        conn = http.client.HTTPConnection(host, port, timeout=30)
        conn.request("GET", "/api/runs/lab/files/manifest.jsonl")  # the control
        res = conn.getresponse()
        assert res.status == 200 and res.read() == (site["root"] / "lab" / "manifest.jsonl").read_bytes()
        conn.close()


def test_symlinks_out_of_root_are_refused(client, site):
    root, outside = site["root"], site["tmp"] / "outside"
    shutil.copy(root / "lab" / "manifest.jsonl", outside / "manifest.jsonl")  # looks like a run folder
    (root / "evil").symlink_to(outside, target_is_directory=True)
    (root / "lab" / "leak.txt").symlink_to(outside / "secret.txt")
    (root / "inside").symlink_to(root / "lab", target_is_directory=True)  # the control: a link inside ROOT
    try:
        assert "evil" not in {r["name"] for r in client.get("/api/runs").json()}
        assert client.get("/api/runs/evil").status_code == 403
        assert client.get("/api/runs/evil/files/secret.txt").status_code == 403
        assert client.get("/api/runs/lab/files/leak.txt").status_code == 403
        assert "leak.txt" not in {f["name"] for f in client.get("/api/runs/lab/files").json()["files"]}
        assert client.get("/api/runs/inside").status_code == 200
        assert client.get("/api/runs/inside/files/manifest.jsonl").status_code == 200
    finally:
        for p in (root / "evil", root / "lab" / "leak.txt", root / "inside"):
            p.unlink()
        (outside / "manifest.jsonl").unlink()


def test_nothing_is_written_and_no_method_but_get(client, site):
    before = _snapshot(site["root"]), _snapshot(site["archive"])
    for url in ("/", "/runs/lab", "/archives/lab", "/api/runs", "/api/runs/lab", "/api/runs/lab/snr.png",
                "/api/runs/full/events", "/api/runs/lab/files?folder=frames", "/api/archive/series?y=0&x=0",
                "/api/archive/preview.png", "/api/archives"):  # fmt: skip
        assert client.get(url).status_code == 200, url
    for method in ("POST", "PUT", "DELETE", "PATCH"):
        for url in ("/api/runs", "/api/runs/lab", "/api/runs/lab/files/manifest.jsonl"):
            assert client.request(method, url).status_code == 405, (method, url)
    assert (_snapshot(site["root"]), _snapshot(site["archive"])) == before


def test_token_is_required_on_every_request_when_set(site):
    app = create_app(site["root"], [site["archive"]], token=TOKEN)
    with TestClient(app, base_url=BASE) as c:
        for url in ("/", "/api/runs", "/api/runs/lab/preview.png", "/static/app.js", "/api/archive/series?y=0&x=0"):
            res = c.get(url)
            assert res.status_code == 401 and res.headers["www-authenticate"] == "Bearer", url
            assert c.get(url, headers={"Authorization": "Bearer wrong-token-0123456789"}).status_code == 401
            assert c.get(url, headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200, url
            assert c.get(url, headers={"X-Hdrcap-Token": TOKEN}).status_code == 200, url
        assert c.get(f"/api/runs?token={TOKEN}x").status_code == 401
        res = c.get(f"/?token={TOKEN}")  # a page opened with the token keeps it in a cookie
        assert (
            res.status_code == 200
            and "HttpOnly" in res.headers["set-cookie"]
            and "SameSite=Strict" in res.headers["set-cookie"]
        )
        assert c.get("/api/runs").status_code == 200  # the cookie now
        c.cookies.clear()
        assert c.get("/api/runs").status_code == 401


def test_off_localhost_needs_a_token():
    with pytest.raises(InputError, match="token"):
        check_bind("0.0.0.0", None)
    with pytest.raises(InputError, match="token"):
        check_bind("192.0.2.7", "")
    with pytest.raises(InputError, match="16 characters"):
        check_bind("0.0.0.0", "short")
    assert check_bind("0.0.0.0", TOKEN) == TOKEN
    assert check_bind("127.0.0.1", None) is None and check_bind("::1", None) is None
    assert all(is_loopback(h) for h in ("localhost", "127.0.0.1", "127.8.9.1", "::1", "[::1]"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "::", "example.org", "10.0.0.1", "localhost.evil.org"))


def test_cli_refuses_another_host_without_a_token(site):
    env = {k: v for k, v in os.environ.items() if k != "HDRCAP_SERVE_TOKEN"}
    proc = subprocess.run(
        [sys.executable, "-m", "hdrcap", "serve", str(site["root"]), "--host", "0.0.0.0"],
        capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip
    assert proc.returncode == 2
    assert (
        proc.stderr.startswith("hdrcap: error: --host 0.0.0.0 serves other machines") and proc.stderr.count("\n") == 1
    )


def test_cli_serves_with_the_token_from_the_environment(site):
    proc = subprocess.Popen(
        [sys.executable, "-m", "hdrcap", "serve", str(site["root"]), "--archive", str(site["archive"]), "--port", "0"],
        env={**os.environ, "HDRCAP_SERVE_TOKEN": TOKEN}, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        line = proc.stderr.readline()
        assert line.startswith("hdrcap serve: http://127.0.0.1:") and "token required" in line
        port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        conn.request("GET", "/api/runs")
        res = conn.getresponse()
        assert res.status == 401
        res.read()
        conn.request("GET", "/api/runs", headers={"Authorization": f"Bearer {TOKEN}"})
        res = conn.getresponse()
        assert res.status == 200 and len(json.loads(res.read())) >= 5
        conn.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) in (0, -signal.SIGTERM)  # uvicorn stops, then ends by the signal it caught


def test_host_header_must_name_this_machine(client):
    """A page elsewhere that points its own name at 127.0.0.1 (DNS rebinding) is answered 400."""
    assert client.get("/api/runs", headers={"Host": "evil.example:8765"}).status_code == 400
    assert client.get("/api/runs", headers={"Host": "localhost:9999"}).status_code == 200
    assert client.get("/api/runs", headers={"Host": "[::1]:8765"}).status_code == 200


def test_security_headers(client):
    res = client.get("/")
    assert res.headers["x-content-type-options"] == "nosniff" and res.headers["x-frame-options"] == "DENY"
    assert "default-src 'self'" in res.headers["content-security-policy"]


def test_missing_extra_is_one_line(monkeypatch, capsys, site):
    import hdrcap.serve
    from hdrcap.cli import main

    monkeypatch.setattr(hdrcap.serve, "REQUIRED", (*hdrcap.serve.REQUIRED, "hdrcap_no_such_package"))
    assert main(["serve", str(site["root"])]) == 2
    err = capsys.readouterr().err
    assert (
        err
        == "hdrcap: error: hdrcap serve needs hdrcap_no_such_package (the serve extra): pip install 'hdrcap[serve]'\n"
    )


# --------------------------------------------------------------------------- memory
def test_a_run_of_5000_frames_is_read_in_bounded_memory(tmp_path, site, monkeypatch):
    """The list, the detail, a page of files and the event tail of a 5000-frame run: no frame is
    read, and the memory Python allocates stays a few MB."""
    import hdrcap.pipeline.io.raw as raw

    run = _big_run(tmp_path / "runs" / "big", site["root"] / "lab", 5000)

    def no_frames(*_a, **_k):
        raise AssertionError("a frame was read")

    monkeypatch.setattr(raw, "read_frame", no_frames)
    app = create_app(tmp_path / "runs")
    with TestClient(app, base_url=BASE) as c:
        c.get("/api/runs")  # imports and first-use allocations out of the measurement
        tracemalloc.start()
        try:
            (entry,) = c.get("/api/runs").json()
            detail = c.get("/api/runs/big").json()
            page = c.get("/api/runs/big/files?folder=frames&offset=4900&limit=50").json()
            with c.stream("GET", "/api/runs/big/events?tail=100") as res:
                tail = [m for m in _sse("".join(res.iter_text())) if m[1] == "event"]
            _size, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert entry["frames_done"] == 5000 and entry["frames_planned"] == 5000 and detail["plan"]["frames"] == 5000
    assert page["total"] == 5000 and len(page["files"]) == 50 and page["files"][0]["name"] == "f4900.dng"
    assert len(tail) == 100 and tail[-1][2]["done"] == 5000
    manifest_mb = (run / "manifest.jsonl").stat().st_size / 1e6
    assert peak < 40e6, f"peak {peak / 1e6:.1f} MB for a {manifest_mb:.1f} MB manifest"


def _big_run(run: Path, like: Path, n: int) -> Path:
    """A run folder of ``n`` recorded frames (tiny files), its manifest and events."""
    head = Manifest(like).header()
    rec = next(r for r in Manifest(like).records() if r["type"] == "frame")
    (run / "frames").mkdir(parents=True)
    keys = [f"light-{i}" for i in range(n)]
    head = {**head, "plan": {**head["plan"], "frames": [{"key": k, "kind": "light", "exposure_s": 0.01} for k in keys]}}
    head.pop("planning", None)
    with open(run / "manifest.jsonl", "w") as f:
        f.write(json.dumps(head) + "\n")
        for i, k in enumerate(keys):
            (run / "frames" / f"f{i:04d}.dng").write_bytes(b"x")
            f.write(json.dumps({**rec, "key": k, "index": i, "file": f"frames/f{i:04d}.dng"}) + "\n")
    with open(run / "events.jsonl", "w") as f:
        f.write(json.dumps({"event": "start", "frames": n, "time": head["time"]}) + "\n")
        for i in range(n):
            f.write(
                json.dumps(
                    {"event": "frame", "key": keys[i], "index": i, "done": i + 1, "total": n, "time": head["time"]}
                )
                + "\n"
            )
    return run


def test_tail_offset(tmp_path):
    p = tmp_path / "e.jsonl"
    p.write_bytes(b"a\nbb\nccc\ndd")  # the last line is still being written
    assert [p.read_bytes()[tail_offset(p, n) :] for n in range(4)] == [
        b"dd",
        b"ccc\ndd",
        b"bb\nccc\ndd",
        b"a\nbb\nccc\ndd",
    ]
    p.write_bytes(b"x" * 200_000 + b"\ny\n")  # lines longer than a block
    assert p.read_bytes()[tail_offset(p, 1) :] == b"y\n" and tail_offset(p, 5) == 0
    assert tail_offset(tmp_path / "missing", 3) == 0


# --------------------------------------------------------------------------- a real browser
@pytest.mark.skipif(
    shutil.which("chromium") is None, reason="headless Chromium not installed (apt-get install chromium)"
)
def test_headless_chromium_renders_the_pages(site, tmp_path):
    """Chromium loads the runs page (the runs named, a screenshot that is not blank) and the
    archive page with a region chosen (the series plot drawn by the page's script)."""
    from PIL import Image

    with live_server(create_app(site["root"], [site["archive"]])) as (host, port):
        base = f"http://{host}:{port}"
        dom = _chromium("--dump-dom", f"{base}/", tmp_path)
        for name in ("cap", "lab", "full", "stopped"):
            assert f'href="/runs/{name}"' in dom
        shot = tmp_path / "runs.png"
        _chromium(f"--screenshot={shot}", f"{base}/", tmp_path)
        pixels = np.asarray(Image.open(shot).convert("L"))
        assert pixels.std() > 10  # not blank
        dom = _chromium("--dump-dom", f"{base}/archives/lab#y=12&x=12&size=4", tmp_path, "--virtual-time-budget=8000")
        assert dom.count('class="dot"') == 2 and "sqrt(sum sigma_i^2) / n" in dom
        # the pictures of docs/serve.md (HDRCAP_SERVE_SCREENSHOTS=docs to write them there)
        shots = {
            "serve_runs.png": (f"{base}/", "--timeout=6000", "1280,560"),
            "serve_run.png": (f"{base}/runs/lab", "--timeout=8000", "1280,1500"),
            "serve_archive.png": (f"{base}/archives/lab#y=12&x=12&size=4", "--virtual-time-budget=8000", "1280,760"),
        }
        for name, (url, wait, size) in shots.items():
            _chromium(f"--screenshot={tmp_path / name}", url, tmp_path, wait, size)
            assert np.asarray(Image.open(tmp_path / name).convert("L")).std() > 10, name
            if os.environ.get("HDRCAP_SERVE_SCREENSHOTS"):
                shutil.copy(tmp_path / name, Path(os.environ["HDRCAP_SERVE_SCREENSHOTS"]) / name)


def _chromium(what: str, url: str, tmp: Path, wait: str = "--timeout=6000", size: str = "1280,900") -> str:
    """Chromium's DOM or screenshot of ``url``. ``wait``: ``--timeout`` for a page with an event
    stream (it never finishes loading), ``--virtual-time-budget`` to let a page's fetches finish."""
    proc = subprocess.run(
        ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--window-size={size}",
         f"--user-data-dir={tmp / 'profile'}", wait, what, url],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout

"""hdrcap.bluesky: HdrDetector under a real RunEngine on the simulated camera. Every document of
every plan is validated against event-model's schemas; the HDF5 maps are `hdrcap merge` of the
frames each run recorded, bit for bit; a camera fault fails the trigger's status with the
session's message and writes nothing; a stopped plan leaves a run folder `hdrcap capture
--resume` finishes."""

from __future__ import annotations

import copy
import json
import math
import threading
import time
from pathlib import Path
from urllib.parse import urlparse

import bluesky.plan_stubs as bps
import bluesky.plans as bp
import h5py
import jsonschema
import numpy as np
import pytest
from bluesky import RunEngine
from bluesky.utils import FailedStatus, RunEngineInterrupted
from event_model import DocumentNames, schema_validators
from ophyd_async.core import TriggerInfo
from ophyd_async.plan_stubs import ensure_connected
from ophyd_async.sim import SimMotor

from hdrcap.bluesky import MAPS, HdrDetector, MapFile
from hdrcap.cli import main
from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.io.exr import read_exr, stored_precisions
from hdrcap.pipeline.result import HdrResult
from hdrcap.pipeline.schema import UNIT_ELECTRONS

TIMES = [0.001, 0.01, 0.1]
SMALL = "48x32"


def validate(docs: list[tuple[str, dict]]) -> None:
    for name, doc in docs:
        schema_validators[DocumentNames[name]].validate(doc)


def run_plan(plan, docs: list | None = None):
    """Run ``plan`` on a new RunEngine (no signal handlers: pytest workers), validate every
    document it emitted, return them (also when the plan failed: ``docs`` is filled as it runs)."""
    docs = [] if docs is None else docs
    RE = RunEngine({}, context_managers=[])
    RE.subscribe(lambda name, doc: docs.append((name, copy.deepcopy(doc))))
    try:
        RE(plan)
    finally:
        validate(docs)
    return docs


def of(docs, name: str) -> list[dict]:
    return [d for n, d in docs if n == name]


def h5_path(stream_resource: dict) -> Path:
    return Path(urlparse(stream_resource["uri"]).path)


def frames_of(run: Path) -> tuple[list[Path], list[Path]]:
    """Light and dark frames of a run folder in capture order (from its manifest)."""
    recs = [json.loads(line) for line in (run / "manifest.jsonl").read_text().splitlines()]
    frames = sorted((r for r in recs if r.get("type") == "frame"), key=lambda r: r["index"])
    return [run / r["file"] for r in frames if r["kind"] == "light"], [
        run / r["file"] for r in frames if r["kind"] == "dark"
    ]


@pytest.fixture(scope="module")
def counted(tmp_path_factory):
    """The issue's example: bp.count of 2 on camera-B, 128x96, a fixed bracket."""
    folder = tmp_path_factory.mktemp("count")
    det = HdrDetector(camera="mock:camera-B", path=folder, name="hdr", times=TIMES, size="128x96")
    docs: list = []
    RE = RunEngine({}, context_managers=[])
    RE.subscribe(lambda name, doc: docs.append((name, copy.deepcopy(doc))))
    RE(ensure_connected(det))
    RE(bp.count([det], num=2))
    validate(docs)
    return folder, docs


def test_count_emits_valid_documents_with_external_maps(counted):
    _folder, docs = counted
    names = [n for n, _d in docs]
    assert names[0] == "start" and names[-1] == "stop" and of(docs, "stop")[0]["exit_status"] == "success"
    assert {"descriptor", "stream_resource", "stream_datum", "event"} <= set(names)
    (desc,) = of(docs, "descriptor")
    keys = desc["data_keys"]
    for m in MAPS:
        key = keys[f"hdr-{m.name}"]
        assert key["external"] == "STREAM:" and key["shape"] == [96, 128]
        assert key["dtype"] == "array" and key["dtype_numpy"] == m.dtype.str
    assert keys["hdr-irradiance"]["units"] == keys["hdr-sigma"]["units"] == UNIT_ELECTRONS
    assert keys["hdr-irradiance"]["dtype_numpy"] == "<f4" and keys["hdr-nexp"]["dtype_numpy"] == "<u4"
    assert keys["hdr-snr_median_db"]["units"] == "dB" and keys["hdr-capture_s"]["units"] == "s"
    assert "external" not in keys["hdr-snr_median_db"]
    config = desc["configuration"]["hdr"]["data"]
    assert config["hdr-camera"] == "mock:camera-B"
    assert json.loads(config["hdr-plan"])["exposure"]["times"] == TIMES
    assert json.loads(config["hdr-calibration"])["params"]["name"] == "camera-B"
    assert json.loads(config["hdr-merge_options"])["exposure_times"] == "effective"
    # one stream resource per map, one datum per map and event, the events' scalars
    resources = of(docs, "stream_resource")
    assert sorted(r["data_key"] for r in resources) == sorted(f"hdr-{m.name}" for m in MAPS)
    assert all(r["parameters"]["join_method"] == "stack" for r in resources)
    datums = of(docs, "stream_datum")
    assert len(datums) == 2 * len(MAPS)
    assert sorted({(d["indices"]["start"], d["indices"]["stop"]) for d in datums}) == [(0, 1), (1, 2)]
    events = of(docs, "event")
    assert len(events) == 2
    for i, ev in enumerate(events):
        data = ev["data"]
        assert not any(f"hdr-{m.name}" in data for m in MAPS)  # external: not in the event
        assert data["hdr-snr_median_db"] > 20 * math.log10(3)
        assert 0 <= data["hdr-saturated_fraction"] < 1 and data["hdr-n_exposures"] == len(TIMES)
        assert math.isnan(data["hdr-snr_target_db"]) and data["hdr-capture_s"] > 0
        assert Path(data["hdr-run_dir"]).name == f"{i:04d}"
    # the HDF5 file: 2 finite frames of each map, median SNR > 3
    (path,) = {h5_path(r) for r in resources}
    with h5py.File(path, "r") as f:
        for m in MAPS:
            assert f[m.name].shape == (2, 96, 128) and f[m.name].dtype == m.dtype
        irr, sig, nexp = f["irradiance"][:], f["sigma"][:], f["nexp"][:]
    assert np.isfinite(irr).all() and np.isfinite(sig).all()
    for k in range(2):
        ok = nexp[k] > 0
        assert np.median(np.abs(irr[k][ok]) / sig[k][ok]) > 3
    assert not np.array_equal(irr[0], irr[1])  # two measurements, not one written twice


def test_maps_are_hdrcap_merge_of_the_recorded_frames_bit_for_bit(counted, tmp_path):
    """Each HDF5 frame equals `hdrcap merge` of its run's frames (sigma at full float precision)."""
    _folder, docs = counted
    (path,) = {h5_path(r) for r in of(docs, "stream_resource")}
    for i, ev in enumerate(of(docs, "event")):
        run = Path(ev["data"]["hdr-run_dir"])
        assert (run / "hdr.exr").is_file()
        assert json.loads((run / "manifest.jsonl").read_text().splitlines()[-1])["type"] == "complete"
        lights, darks = frames_of(run)
        ref = tmp_path / f"merge{i}.exr"
        args = ["merge", *lights, "--darks", *darks, "--camera", "camera-B", "--sigma-precision", "float", "-o", ref]
        assert main([str(a) for a in args]) == 0
        layout = stored_precisions(ref)
        assert layout == {"irradiance": "float", "sigma": "float", "nexp": "uint", "quality": "uint"}
        channels = read_exr(ref).channels  # the uint channels read back as float32 whole numbers
        with h5py.File(path, "r") as f:
            for m in MAPS:
                stored = f[m.name][i]
                assert stored.tobytes() == channels[m.name].astype(m.dtype).tobytes(), (i, m.name)


def test_a_scan_over_a_simulated_motor_measures_once_per_point(tmp_path):
    """The motor's position is the simulated light level (scene_scale follows its readback)."""
    motor = SimMotor(name="lamp", initial_value=1.0)
    det = HdrDetector(path=tmp_path, times=TIMES, size=SMALL, scene_scale=motor.user_readback)
    docs = run_plan(_connected(bp.scan([det, motor], motor, 0.25, 1.0, 3), det, motor))
    events = of(docs, "event")
    assert [ev["data"]["lamp"] for ev in events] == [0.25, 0.625, 1.0]
    assert [ev["data"]["hdr-scene_scale"] for ev in events] == [0.25, 0.625, 1.0]
    assert len({ev["data"]["hdr-run_dir"] for ev in events}) == 3
    (path,) = {h5_path(r) for r in of(docs, "stream_resource")}
    with h5py.File(path, "r") as f:
        irr, nexp = f["irradiance"][:], f["nexp"][:]
    assert irr.shape == (3, 32, 48)
    ok = (nexp > 0).all(axis=0)  # measured at every point
    ratios = [np.median(irr[k][ok] / irr[2][ok]) for k in range(3)]
    assert ratios == pytest.approx([0.25, 0.625, 1.0], rel=0.05)


def test_a_plan_changes_the_target_snr_between_points(tmp_path):
    """det.target_snr_db is a signal: list_scan steps it, each measurement is planned for it."""
    det = HdrDetector(path=tmp_path, times=TIMES, target_snr_db=30.0, size=SMALL, max_exposures=6)
    docs = run_plan(_connected(bp.list_scan([det], det.target_snr_db, [10.0, 15.0]), det))
    events = of(docs, "event")
    assert [ev["data"]["hdr-snr_target_db"] for ev in events] == [10.0, 15.0]
    low, high = (ev["data"] for ev in events)
    assert high["hdr-snr_median_db"] > low["hdr-snr_median_db"]
    for ev in events:  # each run metered and planned for its own target
        head = json.loads((Path(ev["data"]["hdr-run_dir"]) / "manifest.jsonl").read_text().splitlines()[0])
        plan = head["planning"]["plan"]
        assert plan["target_snr_db"] == ev["data"]["hdr-snr_target_db"]
        assert plan["feasible"] and plan["predicted_min_snr_db"] >= plan["target_snr_db"]
        assert len(plan["exposures"]) == ev["data"]["hdr-n_exposures"]
    # NaN: back to the fixed bracket
    det2 = HdrDetector(path=tmp_path / "b", times=TIMES, target_snr_db=25.0, size=SMALL)
    docs = run_plan(_connected(_then_count(bps.mv(det2.target_snr_db, math.nan), det2), det2))
    (ev,) = of(docs, "event")
    assert math.isnan(ev["data"]["hdr-snr_target_db"]) and ev["data"]["hdr-n_exposures"] == len(TIMES)


def test_a_camera_fault_fails_the_status_with_the_sessions_message(tmp_path):
    """The card fills during the second measurement: its trigger fails with the session's
    message; the HDF5 file holds the first measurement only and no datum points further."""
    per_run = 2 * len(TIMES)  # matched darks
    det = HdrDetector(path=tmp_path, times=TIMES, size=SMALL, faults={"card_full_after": per_run + 2})
    docs: list = []
    with pytest.raises(FailedStatus) as info:
        run_plan(_connected(bp.count([det], num=3), det), docs)
    assert "card full" in str(info.value.__cause__) and "--resume" in str(info.value.__cause__)
    stop = of(docs, "stop")[0]
    assert stop["exit_status"] == "fail" and "card full" in stop["reason"]
    assert len(of(docs, "event")) == 1
    datums = of(docs, "stream_datum")
    assert {(d["indices"]["start"], d["indices"]["stop"]) for d in datums} == {(0, 1)}
    (path,) = {h5_path(r) for r in of(docs, "stream_resource")}
    with h5py.File(path, "r") as f:
        assert {f[m.name].shape[0] for m in MAPS} == {1}
    failed = path.with_suffix("") / "0001"
    recs = [json.loads(line) for line in (failed / "manifest.jsonl").read_text().splitlines()]
    assert [r["type"] for r in recs].count("frame") == 2 and recs[-1]["type"] != "complete"


@pytest.fixture
def slow_camera(monkeypatch):
    """The simulated camera takes 0.25 s per frame (time to pause the RunEngine mid-measurement)."""
    from hdrcap.acquire.camera.mock import MockCamera

    capture = MockCamera.capture

    def slow_capture(self, *args, **kwargs):
        time.sleep(0.25)
        return capture(self, *args, **kwargs)

    monkeypatch.setattr(MockCamera, "capture", slow_capture)
    yield
    monkeypatch.setattr(MockCamera, "capture", capture)


def pause_mid_measurement(RE: RunEngine, folder: Path, run: str = "0000") -> threading.Thread:
    """Ctrl-C twice, from another thread: an immediate pause once run ``run`` has two frames."""

    def frames() -> int:
        found = list(folder.glob(f"*/{run}/manifest.jsonl"))
        return found[0].read_text().count('"type":"frame"') if found else 0

    def pause():
        deadline = time.monotonic() + 60
        while frames() < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        RE.request_pause(defer=False)

    thread = threading.Thread(target=pause, daemon=True)
    thread.start()
    return thread


def test_a_stopped_plan_leaves_a_run_folder_capture_resume_finishes(tmp_path, slow_camera):
    """A pause in the middle of a measurement, then RE.stop(): the session stops between two
    frames (a stop event, exit 130), the RunEngine's stop is clean, and `hdrcap capture --resume`
    with the same options finishes the run from the frames it has."""
    det = HdrDetector(path=tmp_path, times=TIMES, size=SMALL)
    RE = RunEngine({}, context_managers=[])
    docs: list = []
    RE.subscribe(lambda name, doc: docs.append((name, copy.deepcopy(doc))))
    pause_mid_measurement(RE, tmp_path)
    with pytest.raises(RunEngineInterrupted):
        RE(_connected(bp.count([det], num=1), det))
    RE.stop()
    validate(docs)
    assert of(docs, "stop")[0]["exit_status"] == "success" and not of(docs, "event")
    (run,) = tmp_path.glob("*/0000")
    recs = [json.loads(line) for line in (run / "manifest.jsonl").read_text().splitlines()]
    done = [r["type"] for r in recs].count("frame")
    assert 2 <= done < 2 * len(TIMES) and recs[-1]["type"] != "complete"
    last = json.loads((run / "events.jsonl").read_text().splitlines()[-1])
    assert last["event"] == "stop" and last["exit_code"] == 130 and "RunEngine" in last["reason"]
    args = ["capture", "--camera", "mock:camera-B", "--times", *TIMES, "--size", SMALL, "--run-dir", run, "--resume"]
    assert main([str(a) for a in args + ["--json", "--no-progress"]]) == 0
    recs = [json.loads(line) for line in (run / "manifest.jsonl").read_text().splitlines()]
    assert recs[-1]["type"] == "complete" and recs[-1]["summary"]["resumed"] == done
    assert (run / "hdr.exr").is_file()


def test_pause_and_resume_measure_the_point_again(tmp_path, slow_camera):
    """Paused mid-measurement, then RE.resume(): the interrupted run folder stays aside, the point
    is measured again in a new one, and each event's datum points at its own row."""
    det = HdrDetector(path=tmp_path, times=TIMES, size=SMALL)
    RE = RunEngine({}, context_managers=[])
    docs: list = []
    RE.subscribe(lambda name, doc: docs.append((name, copy.deepcopy(doc))))
    pause_mid_measurement(RE, tmp_path)
    with pytest.raises(RunEngineInterrupted):
        RE(_connected(bp.count([det], num=2), det))
    RE.resume()
    validate(docs)
    events = of(docs, "event")
    assert [Path(ev["data"]["hdr-run_dir"]).name for ev in events] == ["0001", "0002"]
    assert [(d["indices"]["start"], d["seq_nums"]["start"]) for d in of(docs, "stream_datum")][::4] == [(0, 1), (1, 2)]
    (path,) = {h5_path(r) for r in of(docs, "stream_resource")}
    with h5py.File(path, "r") as f:
        irr = f["irradiance"][:]
    assert irr.shape[0] == 2
    for row, ev in zip(irr, events):
        assert np.array_equal(row, read_exr(Path(ev["data"]["hdr-run_dir"]) / "hdr.exr").channels["irradiance"])
    (interrupted,) = tmp_path.glob("*/0000")
    assert not (interrupted / "hdr.exr").exists()


def test_bad_options_are_refused_before_anything_runs(tmp_path):
    with pytest.raises(InputError, match="camera must be"):
        HdrDetector(camera="nikon", path=tmp_path, times=TIMES)
    with pytest.raises(InputError, match="times"):
        HdrDetector(path=tmp_path)
    with pytest.raises(InputError, match="simulated camera"):
        HdrDetector(camera="gphoto2", path=tmp_path, times=TIMES, calibration="camera-B", size=SMALL)
    with pytest.raises(InputError, match="simulated camera"):
        HdrDetector(camera="gphoto2", path=tmp_path, times=TIMES, calibration="camera-B", scene_scale=2.0)
    (tmp_path / "a-file").write_text("")
    with pytest.raises(InputError, match="not a writable folder"):
        HdrDetector(path=tmp_path / "a-file", times=TIMES)
    (tmp_path / "a-file").unlink()
    det = HdrDetector(path=tmp_path, times=TIMES, size=SMALL)
    with pytest.raises(FailedStatus, match="livetime"):
        run_plan(_connected(bps.prepare(det, TriggerInfo(livetime=0.5), wait=True), det))
    assert not list(tmp_path.iterdir())  # nothing was written


def test_event_model_validation_can_fail(counted):
    """The schema check the tests rely on catches a broken document."""
    _folder, docs = counted
    (desc,) = of(docs, "descriptor")
    broken = copy.deepcopy(desc)
    del broken["data_keys"]["hdr-irradiance"]["shape"]
    with pytest.raises(jsonschema.ValidationError):
        validate([("descriptor", broken)])
    datum = copy.deepcopy(of(docs, "stream_datum")[0])
    del datum["indices"]
    with pytest.raises(jsonschema.ValidationError):
        validate([("stream_datum", datum)])


def test_map_file_appends_whole_measurements(tmp_path):
    shape = (4, 6)
    rng = np.random.default_rng(0)

    def result(quality=True) -> HdrResult:
        irr = rng.random(shape, dtype=np.float32)
        q = np.zeros(shape, np.uint8) if quality else None
        return HdrResult(irr, irr / 10, np.full(shape, 2, np.float32), q)

    f = MapFile(tmp_path / "m.h5")
    f.append(result(), 0)
    f.append(result(), 1)
    with pytest.raises(ValueError, match="quality"):
        f.append(result(quality=False), 2)
    with pytest.raises(ValueError, match="size"):
        f.append(HdrResult(*(np.zeros((2, 2), np.float32) for _ in range(3)), np.zeros((2, 2), np.uint8)), 2)
    assert len(f) == 2
    again = result()
    f.append(again, 1)  # measurement 1 was never announced: replaced, not appended
    f.close()
    with h5py.File(tmp_path / "m.h5", "r") as h5:
        assert h5["irradiance"].shape == (2, 4, 6) and h5["nexp"].dtype == np.uint32
        assert np.array_equal(h5["irradiance"][1], again.irradiance)


def test_tiled_reads_the_run_back(tmp_path):
    """With Tiled installed: a Tiled server and bluesky's TiledWriter serve the maps (N, rows,
    columns) and the scalars of a run, as docs/bluesky.md shows."""
    pytest.importorskip("tiled.server")
    from bluesky.callbacks.tiled_writer import TiledWriter
    from tiled.client import from_uri
    from tiled.server import SimpleTiledServer

    try:
        server = SimpleTiledServer(directory=tmp_path / "catalog", readable_storage=[tmp_path])
    except ModuleNotFoundError as err:  # the client alone, or a partial server install
        pytest.skip(f"Tiled's server side is not installed ({err}): pip install 'tiled[server]'")
    try:
        client = from_uri(server.uri)
        RE = RunEngine({}, context_managers=[])
        RE.subscribe(TiledWriter(client))
        det = HdrDetector(path=tmp_path / "data", times=TIMES, size=SMALL)
        (uid,) = RE(_connected(bp.count([det], num=2), det))
        primary = client[uid]["primary"]
        irr = primary["hdr-irradiance"].read()
        assert irr.shape == (2, 32, 48) and irr.dtype == np.float32
        assert list(primary["hdr-n_exposures"].read()) == [3, 3]
        (path,) = (tmp_path / "data").glob("*.h5")
        with h5py.File(path, "r") as f:
            assert np.array_equal(irr, f["irradiance"][:])
    finally:
        server.close()


def test_the_docs_example_runs(tmp_path, monkeypatch):
    """docs/bluesky.md's first example, as written (count, a motor scan, a target-SNR list_scan)."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "bluesky.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, "docs/bluesky.md", "exec"), namespace)
    files = sorted((tmp_path / "hdr-data").glob("*.h5"))
    assert len(files) == 3
    counts = {}
    for path in files:
        with h5py.File(path, "r") as f:
            counts[path.name.split("-")[0]] = f["irradiance"].shape
    assert counts == {"hdr": (2, 96, 128), "dimmed": (4, 32, 48), "planned": (2, 32, 48)}


def _connected(plan, *devices):
    yield from ensure_connected(*devices)
    return (yield from plan)


def _then_count(first, det):
    yield from first
    return (yield from bp.count([det]))

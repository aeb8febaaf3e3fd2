"""`cadreg load --stream`: a recorded folder played in order as tracked device sessions against a real service
(uvicorn + zenoh on loopback, one worker, a real 7-Scenes site), over zenoh and over HTTP; the table and the JSON
carry the stream keys (DESIGN §8); frame ranges select and concatenate in order."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cadreg.cli.main import main
from clients.load import StreamPlan, parse_ranges, select_indices
from service.settings import Settings
from test_service_support import LiveServer, free_ports
from tracking_support import SITE_ID, redkitchen_site

STREAM_KEYS = {"sent", "answered", "lost", "tracked", "relocalized", "throughput_fps", "latency_ms", "accuracy"}


@pytest.fixture(scope="module")
def server(redkitchen_dir: Path, tmp_path_factory):
    site_dir = redkitchen_site(redkitchen_dir, tmp_path_factory.mktemp("rk-load"))
    port, zport = free_ports(2)
    settings = Settings(sites_dir=site_dir.parent, port=port, workers=1, queue_depth=2, request_timeout_s=60,
                        zenoh_listen=[f"tcp/127.0.0.1:{zport}"], stream_queue_per_device=8)
    live = LiveServer(settings)
    live.zenoh_endpoint = f"tcp/127.0.0.1:{zport}"
    yield live
    live.stop()


def test_ranges_select_and_concatenate_in_order() -> None:
    assert parse_ranges("250:500") == [(250, 500)]
    assert parse_ranges("0:3, 10:12") == [(0, 3), (10, 12)]
    assert select_indices(list(range(20)), "15:18,0:2") == [15, 16, 17, 0, 1]  # the jump of a kidnapped robot
    assert select_indices([0, 2, 4, 6], "1:6") == [2, 4]  # only frames the folder has
    assert select_indices([1, 2], None) == [1, 2]
    for bad in ("5:5", "a:b", "3", "-1:4", ""):
        with pytest.raises(ValueError):
            parse_ranges(bad)
    with pytest.raises(ValueError):
        StreamPlan(devices=0)


def _run(args: list[str], out: Path, capsys) -> tuple[int, dict, str]:
    code = main(["load", *args, "--json", str(out), "--no-progress"])
    return code, json.loads(out.read_text()), capsys.readouterr().out


def test_zenoh_stream_reports_tracked_frames(server, redkitchen_dir: Path, tmp_path: Path, capsys) -> None:
    code, summary, table = _run(["--zenoh", server.zenoh_endpoint, "--site", SITE_ID, "--frames", str(redkitchen_dir),
                                 "--stream", "--range", "250:262", "--rate", "8", "--device", "bot"],
                                tmp_path / "z.json", capsys)
    assert STREAM_KEYS <= set(summary) and {"p50", "p90", "p99", "max"} <= set(summary["latency_ms"])
    assert {"success_5cm_5deg", "median_translation_m"} <= set(summary["accuracy"])
    assert summary["mode"] == "stream" and summary["devices"] == 1
    assert summary["warmup"]["frames"] == 1 and summary["warmup"]["modes"] == ["global"]
    assert summary["sent"] == 11 and summary["answered"] + summary["lost"] == summary["sent"]
    assert summary["answered"] >= 10 and summary["tracked"] >= 9, summary
    assert summary["accuracy"]["success_5cm_5deg"] >= 0.9
    assert summary["tracked_worker_ms"]["p50"] is not None
    assert "tracked / relocalized / global" in table and "answered / lost" in table
    assert code == 0


def test_http_stream_plays_several_devices(server, redkitchen_dir: Path, tmp_path: Path, capsys) -> None:
    code, summary, _ = _run(["--url", server.url, "--site", SITE_ID, "--frames", str(redkitchen_dir), "--stream",
                             "--range", "250:256,250:256", "--rate", "5", "--devices", "2", "--device", "hbot"],
                            tmp_path / "h.json", capsys)
    # 12 frames each, the first as warm-up; each device its own session
    assert summary["sent"] == 22 and summary["devices"] == 2 and summary["lost"] == 0
    assert summary["answered"] == 22 and summary["tracked"] >= 16, summary
    assert code == 0


def test_a_stream_of_n_frames_reads_only_those(server, redkitchen_dir: Path, tmp_path: Path, capsys, caplog) -> None:
    # --n 4 of the whole 500-frame folder: four frames read and encoded (not 147 MB of them), played in order
    caplog.set_level("INFO", logger="cadreg.load")
    code, summary, _ = _run(["--url", server.url, "--site", SITE_ID, "--frames", str(redkitchen_dir), "--stream",
                             "--range", "250:500", "--n", "4", "--rate", "5"], tmp_path / "n.json", capsys)
    assert "encoded 4 frames" in caplog.text, caplog.text
    assert summary["sent"] == 3 and summary["warmup"]["frames"] == 1 and summary["answered"] == 3, summary
    assert code == 0

"""MCAP flight logs (``groundstation.mcap_log``): one short flight against simulated Crazyflies is written to an
MCAP and a JSON-lines log at once; the MCAP is read back with the ``mcap`` reader (schemas, channels, message
counts, the Foxglove messages) and its rows equal the JSON-lines log's, positions included."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("cflib")
pytest.importorskip("mcap")

from flight_fixtures import open_sim_links, quick_flight, small_spec, wait_until  # noqa: E402
from groundstation.demo import draw_obstacles, start_positions  # noqa: E402
from groundstation.flight import DroneStatus, FlightSession, JsonlRecorder, close_links  # noqa: E402
from groundstation.liveview import scene  # noqa: E402
from groundstation.mcap_log import LogError, McapRecorder, open_recorder, read_log  # noqa: E402
from groundstation.positioning import AnchorLayout  # noqa: E402
from groundstation.roles import PURSUER_TEAM  # noqa: E402
from groundstation.safety import FenceConfig  # noqa: E402
from groundstation.sim.swarm import SimSwarm, free_base_port  # noqa: E402


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """(mcap path, jsonl path, ids) of one hover flight of 3 drones, recorded in both formats."""
    out = tmp_path_factory.mktemp("mcap")
    spec = small_spec()
    fence = FenceConfig.from_spec(spec, draw_obstacles(spec, seed=7))
    sc = scene(fence, AnchorLayout(), spec)
    n = 3
    ids = [f"cf{i}" for i in range(n)]
    mcap_rec = open_recorder(out / "flight.mcap", sc)
    jsonl_rec = open_recorder(out / "flight.jsonl", sc)
    assert isinstance(mcap_rec, McapRecorder) and isinstance(jsonl_rec, JsonlRecorder)

    def tee(row: dict) -> None:
        mcap_rec(row)
        jsonl_rec(row)

    with SimSwarm(n, base_port=free_base_port(n, seed=31), seed=7,
                  start_positions=start_positions(fence, n, seed=7)) as sims:
        links = open_sim_links(sims.uris)
        try:
            session = FlightSession(dict(zip(ids, links)), {d: PURSUER_TEAM for d in ids}, fence, quick_flight(),
                                    record=tee)
            with session:
                session.preflight()
                session.takeoff()
                t_up = session.time()
                assert wait_until(lambda: session.time() - t_up > 1.0, timeout=5)
                tee({"t": round(session.time(), 4), "event": "metrics", "drone": None, "detail": "",
                     "mean_min_dist": 1.0, "mean_avg_dist": 1.5, "mean_max_dist": 2.0, "tracking_rate": 0.5,
                     "coverage": 0.25, "episodes": 0, "steps": 10})
                session.land_all()
                assert set(session.statuses().values()) == {DroneStatus.LANDED}
        finally:
            close_links(links)
            mcap_rec.close()
            jsonl_rec.close()
    return out / "flight.mcap", out / "flight.jsonl", ids


def test_mcap_schemas_channels_and_counts(logs):
    from mcap.reader import make_reader
    mcap_path, jsonl_path, ids = logs
    rows = read_log(jsonl_path)
    state = [r for r in rows if "event" not in r]
    events = [r for r in rows if "event" in r and r["event"] not in ("scene", "metrics")]
    with mcap_path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        schemas = {s.id: s for s in summary.schemas.values()}
        channels = {c.topic: c for c in summary.channels.values()}
        counts = {channels_topic: summary.statistics.channel_message_counts[c.id]
                  for channels_topic, c in channels.items()}
        for c in channels.values():
            assert c.message_encoding == "json" and schemas[c.schema_id].encoding == "jsonschema"
            json.loads(schemas[c.schema_id].data)  # every schema is JSON Schema
        names = {t: schemas[c.schema_id].name for t, c in channels.items()}
        assert names["/scene"] == "foxglove.SceneUpdate" and names["/drones/poses"] == "foxglove.PosesInFrame"
        assert names["/log"] == "foxglove.Log" and names["/events"] == "swarmpursuit.Event"
        assert names["/metrics"] == "swarmpursuit.Metrics" and names["/scene/static"] == "swarmpursuit.Scene"
        for d in ids:
            assert names[f"/drones/{d}/status"] == "swarmpursuit.DroneStatus"
            assert names[f"/drones/{d}/setpoint"] == "swarmpursuit.Setpoint"
            assert counts[f"/drones/{d}/status"] == sum(1 for r in state if r["drone"] == d) > 10
            assert counts[f"/drones/{d}/setpoint"] == sum(1 for r in state if r["drone"] == d and r["setpoint"])
        assert counts["/events"] == counts["/log"] == len(events) > 0
        assert counts["/metrics"] == 1 and counts["/scene/static"] == 1
        with_pos = [r for r in state if r["position"] is not None]
        assert counts["/scene"] == 1 + len(with_pos)
        assert counts["/drones/poses"] == len({r["t"] for r in with_pos})
        # the Foxglove messages themselves
        msgs = {}
        for _, channel, message in reader.iter_messages(topics=["/scene", "/log", "/drones/poses"]):
            msgs.setdefault(channel.topic, []).append(json.loads(message.data))
    static = {e["id"] for e in msgs["/scene"][0]["entities"]}
    assert {"fence", "keep_out/0", "anchor/0"} <= static and len(static) == 1 + 3 + 8
    drone = msgs["/scene"][-1]["entities"][0]
    assert drone["id"].startswith("drone/") and drone["frame_id"] == "world" and len(drone["spheres"]) == 1
    assert set(drone["spheres"][0]["pose"]["position"]) == {"x", "y", "z"}
    levels = {m["message"].split(":")[0]: m["level"] for m in msgs["/log"]}
    assert levels["preflight_ok"] == 2 and all(set(m["timestamp"]) == {"sec", "nsec"} for m in msgs["/log"])
    assert max(len(m["poses"]) for m in msgs["/drones/poses"]) == len(ids)


def test_mcap_rows_equal_the_jsonl_log(logs):
    mcap_path, jsonl_path, ids = logs
    a, b = read_log(mcap_path), read_log(jsonl_path)
    assert len(a) == len(b)
    key = lambda r: json.dumps(r, sort_keys=True)  # noqa: E731
    assert sorted(map(key, a)) == sorted(map(key, b))
    for d in ids:  # one flight's positions, in order
        pa = [r["position"] for r in a if r.get("drone") == d and "event" not in r]
        pb = [r["position"] for r in b if r.get("drone") == d and "event" not in r]
        assert pa == pb and any(p is not None and p[2] > 0.3 for p in pa)
    assert a[0]["event"] == "scene" and a[0]["scene"]["fence"]["margin"] > 0


def test_unreadable_logs_name_the_file(tmp_path):
    with pytest.raises(LogError, match="no such flight log"):
        read_log(tmp_path / "missing.mcap")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(LogError, match="bad.mcap"):
        read_log(bad)
    cut = tmp_path / "cut.jsonl"
    cut.write_text('{"t": 0.0, "event": "scene"}\n{"t": 0.1, "dro')  # a log cut short mid-row
    assert read_log(cut) == [{"t": 0.0, "event": "scene"}]
    junk = tmp_path / "junk.jsonl"
    junk.write_text("hello\n")
    with pytest.raises(LogError, match="junk.jsonl:1"):
        read_log(junk)


def test_replay_and_report_take_either_format(logs, capsys):
    from groundstation import cli
    from groundstation.replay import ReplaySource
    mcap_path, jsonl_path, ids = logs
    for path in (mcap_path, jsonl_path):
        source = ReplaySource(read_log(path))
        source.control("replay", {"pause": True, "seek": 1e9})
        s = source.state()
        assert [d["id"] for d in s["drones"]] == ids and {d["status"] for d in s["drones"]} == {"landed"}
        assert s["scene"]["fence"] and s["metrics"]["mean_avg_dist"] == 1.5
        assert any(e["kind"] == "preflight_ok" for e in s["events"]) and not s["mission"]
    # a hover flight flies no actors: the paper's metrics cannot be computed, in one line naming LOG
    assert cli.main(["report", str(jsonl_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("swarm-gs report: error: LOG") and "evader" in err and err.count("\n") == 1
    with pytest.raises(SystemExit) as exit_:
        cli.main(["replay", str(jsonl_path.with_name("nothing.jsonl"))])
    assert exit_.value.code == 2 and "nothing.jsonl" in capsys.readouterr().err


def test_an_mcap_cut_short_reads_up_to_the_cut(tmp_path):
    """A process killed mid-flight leaves an MCAP without its summary: read_log reads the chunks written."""
    import subprocess
    import sys
    path = tmp_path / "cut.mcap"
    code = ("import os\nfrom groundstation.mcap_log import McapRecorder\n"
            f"r = McapRecorder({str(path)!r}, chunk_size=2048)\n"
            "for k in range(300):\n"
            "    r({'t': round(k * 0.1, 4), 'drone': 'cf0', 'role': 'pursuer', 'actor': 'pursuer_0', 'state': 'flying',"
            " 'position': [k * 0.01, 0.0, 0.5], 'setpoint': None, 'battery': 3.9, 'link_quality': 1.0,"
            " 'telemetry_age': 0.0})\n"
            "os._exit(0)  # killed: no close, no summary\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
    rows = read_log(path)
    assert 50 < len(rows) <= 300
    assert [r["t"] for r in rows] == [round(k * 0.1, 4) for k in range(len(rows))]  # a prefix, in order

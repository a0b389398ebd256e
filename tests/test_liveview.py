"""The live view (``groundstation.liveview``) during real flights against simulated Crazyflies through cflib.

A demo-like flight (``run_demo`` with 5 drones: 2 pursuers, 2 scouts, 1 evader) is shown in a ``LiveView``: its
``/api/state`` is read, two WebSockets receive the pushed state at >= 10 Hz, a refused emergency stop (no
confirmation) and an unknown drone change nothing, and "land all" through ``POST /api/land_all`` brings every
drone down, which ends the demo's mission. A second, short hover flight checks that the confirmed emergency
stop cuts every simulated drone's motors, and that a taken port is a one-line error naming --view.
"""
from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
import urllib.error
import urllib.request

import pytest

pytest.importorskip("cflib")
pytest.importorskip("aiohttp")

from flight_fixtures import open_sim_links, quick_flight, small_spec, wait_until, write_fleet, write_models  # noqa: E402
from groundstation.demo import DemoError, DemoOptions, draw_obstacles, run_demo, start_positions  # noqa: E402
from groundstation.flight import DroneStatus, FlightSession, close_links  # noqa: E402
from groundstation.liveview import LiveView, SessionSource, ViewError, scene  # noqa: E402
from groundstation.roles import PURSUER_TEAM  # noqa: E402
from groundstation.safety import FenceConfig  # noqa: E402
from groundstation.sim.swarm import SimSwarm, free_base_port  # noqa: E402


def tolerant_flight(folder) -> "Path":
    """A [flight] TOML whose failsafes wait longer (link loss after 1 s of silence, a stale position after 0.5 s):
    these tests check the view, not the failsafes, and a very loaded machine can pause the simulators' process
    for a few hundred ms; takeoff and landing at ``quick_flight``'s pace."""
    from pathlib import Path
    from flight_fixtures import quick_flight_toml
    return quick_flight_toml(Path(folder) / "tolerant_flight.toml", link_loss_timeout=1.0, position_stale_after=0.5,
                             position_hold_time=1.0, command_timeout=1.0)


def get_state(view: LiveView) -> dict:
    with urllib.request.urlopen(view.url + "api/state", timeout=5) as r:
        assert r.headers["Content-Type"].startswith("application/json")
        return json.loads(r.read())


def post(view: LiveView, path: str, body: dict | None = None) -> tuple[int, dict]:
    req = urllib.request.Request(view.url + path.lstrip("/"), data=json.dumps(body or {}).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def receive(view: LiveView, count: int, tabs: int = 2, timeout: float = 30.0, span: float = 1.0) -> list[list[dict]]:
    """The messages each of ``tabs`` WebSockets received until it had ``count`` of them spanning ``span`` s of the
    state's own clock ``t`` (each waits at most ``timeout`` s: the rate a loaded machine achieves is a benchmark
    figure, BENCHMARKS.md, not a test's)."""
    import aiohttp

    async def one(session) -> list[dict]:
        out = []
        async with session.ws_connect(view.url.replace("http", "ws") + "ws") as ws:
            t0 = time.monotonic()
            while ((len(out) < count or out[-1].get("t", 0.0) - out[0].get("t", 0.0) < span)
                   and time.monotonic() - t0 < timeout):
                msg = await ws.receive(timeout=timeout)
                out.append(json.loads(msg.data))
        return out

    async def main():
        async with aiohttp.ClientSession() as session:
            return await asyncio.gather(*(one(session) for _ in range(tabs)))

    return asyncio.run(main())


@pytest.fixture(scope="module")
def demo_flight(tmp_path_factory):
    """A 5-drone demo shown in a view; the test lands it from the view. Yields (view, box) with the demo's
    result (or exception) in box once its thread ends."""
    models = write_models(tmp_path_factory.mktemp("liveview-models") / "m", small_spec(), seed=2)
    view = LiveView(port=0).start()
    box: dict = {"log": tmp_path_factory.mktemp("liveview-log") / "flight.mcap"}

    def fly():
        try:
            box["result"] = run_demo(DemoOptions(duration=40.0, models=str(models), seed=4, log_path=str(box["log"]),
                                                 flight=str(tolerant_flight(models.parent))), view=view)
        except BaseException as exc:  # handed to the test
            box["error"] = exc

    thread = threading.Thread(target=fly, name="demo", daemon=True)
    thread.start()
    box["thread"] = thread
    try:
        yield view, box
    finally:
        if thread.is_alive():  # a failed test: land whatever flies, through the view
            post(view, "/api/land_all")
        thread.join(timeout=60)
        view.stop()


def test_state_websocket_and_land_all_from_the_view(demo_flight):
    view, box = demo_flight
    ids = [f"cf{i}" for i in range(5)]

    def mission_flying() -> bool:
        s = get_state(view)
        return s["mode"] == "live" and s["mission"] and [d["status"] for d in s["drones"]] == ["flying"] * 5

    assert wait_until(mission_flying, timeout=60, period=0.1), (get_state(view), box.get("error"))
    s = get_state(view)
    assert [d["id"] for d in s["drones"]] == ids
    for d in s["drones"]:
        for key in ("id", "role", "actor", "status", "position", "battery", "link_quality", "position_variance",
                    "command_age", "telemetry_age"):
            assert key in d, key
        assert len(d["position"]) == 3 and d["position"][2] > 0.2 and 3.0 < d["battery"] < 4.3
        assert 0.0 <= d["link_quality"] <= 1.0 and d["telemetry_age"] < 1.0
    assert sorted(d["role"] for d in s["drones"]) == ["evader", "pursuer", "pursuer", "scout", "scout"]
    sc = s["scene"]
    assert len(sc["fence"]["polygon"]) >= 3 and sc["fence"]["margin"] > 0 and len(sc["keep_out"]) >= 1
    assert len(sc["anchors"]) == 8 and sc["sensing_range"] > 0 and sc["arena"]["half_width"] > 0
    assert any(e["kind"] == "mission_start" for e in s["events"])
    assert set(s["controls"]) == {"land_all", "land", "emergency_stop"}
    # the paper's metrics, live
    assert wait_until(lambda: get_state(view)["metrics"].get("steps", 0) > 0, timeout=10, period=0.1)
    m = get_state(view)["metrics"]
    assert 0 < m["mean_min_dist"] <= m["mean_avg_dist"] <= m["mean_max_dist"]
    assert 0 <= m["tracking_rate"] <= 1 and 0 < m["coverage"] <= 1

    # two tabs at once, each getting the pushes (configured at >= 10 a second), the drones moving in them
    assert view.rate >= 10
    frames0 = view.frames
    tabs = receive(view, 10, tabs=2)
    for msgs in tabs:
        assert len(msgs) >= 10, len(msgs)
        assert {len(m["drones"]) for m in msgs} == {5}
        assert msgs[-1]["t"] > msgs[0]["t"]
    assert view.frames - frames0 >= 9  # a tab's first message is the frame pushed before it connected

    # refused: an emergency stop without its confirmation, a drone that is not flown
    code, out = post(view, "/api/emergency_stop", {})
    assert code == 400 and "confirm" in out["error"]
    code, out = post(view, "/api/emergency_stop", {"confirm": "yes"})
    assert code == 400
    code, out = post(view, "/api/land/cf99")
    assert code == 400 and "cf99" in out["error"]
    code, out = post(view, "/api/land_all", [1, 2])
    assert code == 400
    s = get_state(view)  # nothing stopped (a loaded machine may land a drone on its own failsafe: not checked here)
    assert "stopped" not in {d["status"] for d in s["drones"]} and not any(e["kind"] == "emergency_stop"
                                                                          for e in s["events"])

    # land all, through the session
    code, out = post(view, "/api/land_all")
    assert code == 200 and out["ok"] and set(out["statuses"]) == set(ids)
    # every drone lands ("lost": a link that timed out on a very loaded machine, brought down by its watchdog)
    down = {"landed", "lost"}
    assert wait_until(lambda: {d["status"] for d in get_state(view)["drones"]} <= down, timeout=20,
                      period=0.1), get_state(view)["drones"]
    box["thread"].join(timeout=60)
    assert "error" not in box, box.get("error")
    res = box["result"]
    assert res["landed"] == 5 and set(res["final_status"].values()) <= down
    assert "landed" in res["final_status"].values()
    assert res["mission_s"] < 30  # the land-all ended the 40 s mission
    # the view keeps the final state, without controls: the web server has it from the view's next push (every
    # 1 / rate s; CI once read the last live state right after the demo returned, on a loaded machine)
    assert wait_until(lambda: get_state(view)["controls"] == [], timeout=10, period=0.05), get_state(view)["controls"]
    s = get_state(view)
    assert s["mission"] is False and {d["status"] for d in s["drones"]} <= down
    code, _ = post(view, "/api/land_all")
    assert code == 409
    # the demo's --log flight.mcap: the scene first, the metrics every second, every drone's rows
    from groundstation.mcap_log import read_log
    rows = read_log(box["log"])
    assert rows[0]["event"] == "scene" and rows[0]["scene"] == s["scene"]
    assert any(r.get("event") == "metrics" and "mean_avg_dist" in r for r in rows)
    assert {r["drone"] for r in rows if "event" not in r} == set(ids)
    assert any(r.get("event") == "status" and "live view: land all" in r["detail"] for r in rows)


def test_emergency_stop_from_the_view_cuts_every_motor(tmp_path):
    spec = small_spec()
    obstacles = draw_obstacles(spec, seed=5)
    fence = FenceConfig.from_spec(spec, obstacles)
    n = 3
    ids = [f"cf{i}" for i in range(n)]
    with LiveView(port=0) as view, SimSwarm(n, base_port=free_base_port(n, seed=23), seed=5,
                                            start_positions=start_positions(fence, n, seed=5)) as sims:
        links = open_sim_links(sims.uris)
        try:
            session = FlightSession(dict(zip(ids, links)), {d: PURSUER_TEAM for d in ids}, fence, quick_flight())
            view.attach(SessionSource(session, scene(fence)))
            with session:
                session.preflight()
                session.takeoff()
                assert session.flying() == ids
                assert all(sims.truth(i).motors_on for i in range(n))
                code, out = post(view, "/api/emergency_stop", {"confirm": True})
                assert code == 200 and set(out["statuses"].values()) == {"stopped"}
                assert wait_until(lambda: all(not sims.truth(i).motors_on for i in range(n)), timeout=5)
                assert all(sims.truth(i).supervisor == "locked" for i in range(n))
                assert session.statuses() == {d: DroneStatus.STOPPED for d in ids}
                assert len(session.events_of("emergency_stop")) == 1
                assert wait_until(lambda: any(e["kind"] == "emergency_stop" for e in get_state(view)["events"]),
                                  timeout=5, period=0.05)
                assert {d["status"] for d in get_state(view)["drones"]} == {"stopped"}
        finally:
            close_links(links)


def test_a_taken_port_is_one_line_naming_view(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        with pytest.raises(ViewError) as err:
            LiveView(port=port).start()
        msg = str(err.value)
        assert f"--view {port}" in msg and "taken" in msg and "\n" not in msg
        # the demo refuses before any simulator starts
        models = write_models(tmp_path / "m", small_spec())
        t0 = time.monotonic()
        with pytest.raises(DemoError, match="--view"):
            run_demo(DemoOptions(duration=1.0, models=str(models), view_port=port))
        assert time.monotonic() - t0 < 10


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_fly_view_lands_a_fleet_and_a_taken_port_is_refused(tmp_path, capsys):
    from pathlib import Path

    from groundstation import cli
    root = Path(__file__).resolve().parents[1]
    spec = small_spec()
    models = write_models(tmp_path / "models", spec, seed=4)
    (tmp_path / "spec.toml").write_text("[spec.team]\nn_pursuers = 2\nn_scouts = 2\nn_evaders = 1\n")
    fence = FenceConfig.from_toml(root / "configs" / "fence.toml")
    n = 3
    with SimSwarm(n, base_port=free_base_port(n, seed=29), seed=4, start_positions=start_positions(fence, n, 4)) \
            as sims:
        fleet = write_fleet(tmp_path / "fleet.toml", models, tmp_path / "spec.toml", sims.uris, root)
        # a taken port: one line naming --view, before any link opens
        with socket.socket() as taken:
            taken.bind(("127.0.0.1", 0))
            taken.listen(1)
            busy = taken.getsockname()[1]
            assert cli.main(["fly", "--fleet", str(fleet), "--duration", "1", "--view", str(busy)]) == 2
            err = capsys.readouterr().err
            assert f"--view {busy}" in err and "taken" in err and err.count("\n") == 1
            assert all(not sims.truth(i).motors_on for i in range(n))
        port = _free_port()
        view = LiveView(port=port)  # only its url: the CLI's own view serves
        box: dict = {}

        def operator():  # the CLI flies on the main thread (its Ctrl-C handler); the "browser" is this thread
            def flying() -> bool:
                try:
                    s = get_state(view)
                except OSError:
                    return False
                box["last"] = s
                return s["mode"] == "live" and s["mission"] and {d["status"] for d in s["drones"]} == {"flying"}
            box["flying"] = wait_until(flying, timeout=30, period=0.1)
            box["land_all"] = post(view, "/api/land_all")  # also when the wait failed: never leave them up

        watcher = threading.Thread(target=operator, daemon=True)
        watcher.start()
        t0 = time.monotonic()
        box["rc"] = cli.main(["fly", "--fleet", str(fleet), "--duration", "30", "--view", str(port)])
        assert time.monotonic() - t0 < 25  # the land-all ended the 30 s mission
        watcher.join(timeout=10)
        assert box["flying"], box.get("last")
        assert "metrics" in box["last"] and len(box["last"]["drones"]) == n
        assert box["land_all"][0] == 200
        assert box["rc"] == 0
        out = capsys.readouterr().out
        assert f"live view: http://127.0.0.1:{port}/" in out and "'cf2': 'landed'" in out
        assert all(not sims.truth(i).motors_on for i in range(n))


def test_replay_and_report_of_the_demo_log(demo_flight, tmp_path, capsys):
    """The demo's MCAP log (written by the first test's flight) played into a view and reported."""
    from groundstation import cli
    from groundstation.mcap_log import read_log
    from groundstation.replay import ReplaySource, report
    view, box = demo_flight
    box["thread"].join(timeout=60)
    assert box["log"].is_file(), "the demo flight did not run"
    rows = read_log(box["log"])
    res = report(rows)
    final = box["result"]["final_status"]  # as the session ended (on a loaded machine a drone may be "lost")
    landed = sum(1 for v in final.values() if v == "landed")
    assert res["final_state"] == final
    # one episode per episode_steps mission steps, the last one cut short (1 when the first test landed the
    # flight from the view; 4 when this test runs alone and the 40 s mission flies to its end)
    episodes = -(-res["steps"] // small_spec().timing.episode_steps)
    assert res["drones"] == 5 and res["landed"] == landed and res["steps"] > 5 and res["episodes"] == episodes
    assert 0 < res["mean_min_dist"] <= res["mean_avg_dist"] <= res["mean_max_dist"]
    assert 0 <= res["tracking_rate"] <= 1 and 0 < res["coverage"] <= 1
    assert cli.main(["report", str(box["log"]), "--plot", str(tmp_path / "r.png"), "--json",
                     str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    assert "distance to targets" in out and f"landed {landed}/5" in out
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "r.json").read_text())["steps"] == res["steps"]

    source = ReplaySource(rows, speed=1.0)
    with LiveView(port=0) as replay:
        replay.attach(source)
        assert wait_until(lambda: len(get_state(replay)["drones"]) == 5, timeout=5, period=0.05)
        s = get_state(replay)
        assert s["mode"] == "replay" and s["controls"] == ["replay"] and s["scene"]["fence"]
        assert s["replay"]["duration"] > 1.0
        code, out = post(replay, "/api/replay", {"pause": True, "seek": 1.0})
        assert code == 200 and out["replay"]["paused"] and out["replay"]["t"] == 1.0
        assert wait_until(lambda: get_state(replay)["replay"]["t"] == 1.0, timeout=5, period=0.05)
        t1 = get_state(replay)["t"]
        assert abs(t1 - (source.t_begin + 1.0)) < 1e-6
        assert get_state(replay)["t"] == t1  # paused
        # the drones where the log has them at that time
        for d in get_state(replay)["drones"]:
            logged = [r for r in rows if r.get("drone") == d["id"] and "event" not in r and r["t"] <= t1][-1]
            assert d["position"] == logged["position"]
            later = [r["to"] for r in rows if r.get("event") == "status" and r.get("drone") == d["id"]
                     and logged["t"] < r["t"] <= t1]  # a status change between two record periods shows at once
            assert d["status"] == (later[-1] if later else logged["state"])
        code, out = post(replay, "/api/replay", {"seek": 1e9, "pause": False, "speed": 8})
        assert code == 200
        assert wait_until(lambda: source.finished, timeout=5, period=0.05)
        assert wait_until(lambda: {d["id"]: d["status"] for d in get_state(replay)["drones"]} == final, timeout=5,
                          period=0.05)
        code, _ = post(replay, "/api/replay", {"speed": -1})
        assert code == 400
        code, _ = post(replay, "/api/land_all")
        assert code == 409  # a replay commands no drone
    # swarm-gs replay --once: plays to the end and exits
    port = _free_port()
    assert cli.main(["replay", str(box["log"]), "--view", str(port), "--speed", "50", "--once"]) == 0
    assert f"live view: http://127.0.0.1:{port}/" in capsys.readouterr().out


class _CountingSource:
    """A source whose every state is fresh; counts the states asked for and the controls run."""

    controls = ("land_all",)

    def __init__(self) -> None:
        self.states = 0
        self.ran: list[str] = []

    def state(self) -> dict:
        self.states += 1
        return {"mode": "live", "t": self.states * 0.05, "mission": True, "drones": [], "events": [],
                "controls": list(self.controls), "scene": None, "odd": float("nan")}

    def control(self, name: str, args: dict) -> dict:
        self.ran.append(name)
        return {"ok": True, "control": name}


def test_the_web_server_runs_outside_the_ground_stations_interpreter(monkeypatch):
    """Tabs cost the ground station nothing: the state is encoded and pushed by the server's own process (no JSON
    encoding in this interpreter while three tabs read at >= 10 Hz), and a server that dies takes nothing with it:
    the source is no longer asked, and stop() is prompt."""
    import os

    encodes = []
    real = json.dumps
    monkeypatch.setattr(json, "dumps", lambda *a, **k: (encodes.append(1), real(*a, **k))[1])
    source = _CountingSource()
    view = LiveView(port=0).start()
    try:
        assert view._proc.pid != os.getpid()
        view.attach(source)
        tabs = receive(view, 10, tabs=3)
        assert all(len(msgs) >= 10 for msgs in tabs), [len(m) for m in tabs]
        assert tabs[0][-1]["odd"] is None  # strict JSON, encoded over there
        assert wait_until(lambda: view.clients == 0, timeout=5)
        assert encodes == []
        code, out = post(view, "/api/land_all")
        assert code == 200 and source.ran == ["land_all"]
        view._proc.kill()
        assert wait_until(lambda: not view._threads[0].is_alive(), timeout=10)  # the feed ended
        asked = source.states
    finally:
        t0 = time.monotonic()
        view.stop()
        assert time.monotonic() - t0 < 5
    assert source.states == asked

"""The bridge's MQTT output against a real Home Assistant.

Runs Home Assistant core (pinned in requirements.txt, in the virtual
environment setup.sh makes) with its MQTT integration set up by a config
entry (through the config flow, as the UI does), Debian's mosquitto on
loopback, and the bridge's MQTT output from `sim` (the firmware's publisher
and session). Reads what Home Assistant made of it through its own REST and
WebSocket APIs and checks:

* every entity of docs/home-assistant.md exists with its unit, device class,
  state class and category, under one device per BMS;
* its value equals what the bridge published (the state message, taken from
  the broker);
* a hung bridge (SIGSTOP) turns every entity unavailable within the
  documented bound; a killed connection at once; both come back;
* Home Assistant restarted: the entities come back with values;
* discovery off: the entities and the device are removed;
* two simulated bridges: two devices that do not disturb each other;
* several packs: every pack's device and the battery's;
* the energy entities are accepted by the Energy dashboard's own validation;
* Home Assistant's log has no warning or error about any of it.

Usage: python check.py PATH/TO/sim   (the venv's python; exit 1 on a failure)
Every wait is bounded; every process started is stopped at the end.
"""

import asyncio
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from datetime import timedelta
from pathlib import Path

import aiohttp
import paho.mqtt.client as mqtt

ROOT = Path(__file__).resolve().parents[2]
GUIDE = ROOT / "docs" / "home-assistant.md"

# The documented bound: 3 publish periods, at least 15 s (15 s at the
# default period). Home Assistant's timer and this poll add a little.
EXPIRE_S = 15
SLACK_S = 2.0
# A closed connection: the broker publishes the will at once.
KILLED_BOUND_S = 3.0


class Failed(Exception):
    pass


def check(ok, what):
    if not ok:
        raise Failed(what)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(what, cond, timeout, step=0.25, why=None):
    """cond() until it is truthy; its value. Fails after `timeout` s
    (saying `why()` when given)."""
    end = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() >= end:
            raise Failed(f"{what}: not within {timeout} s" + (f" ({why()})" if why else ""))
        time.sleep(step)


def guide_tables():
    """The entity tables of the guide: (pack rows, battery rows), each row
    (object, name, platform, device class, state class, unit, member)."""
    tables, current = [], None
    for line in GUIDE.read_text().splitlines():
        if line.startswith("| object | name | platform |"):
            current = []
            tables.append(current)
        elif current is not None and line.startswith("| `"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            current.append([c.strip("`") for c in cells])
        elif current is not None and not line.startswith("| ---"):
            current = None
    check(len(tables) == 2, f"the guide has {len(tables)} entity tables, not 2")
    return tables[0], tables[1]


class Broker:
    def __init__(self, tmp):
        self.port = free_port()
        conf = tmp / "mosquitto.conf"
        conf.write_text(
            f"listener {self.port} 127.0.0.1\nallow_anonymous true\n"
            "persistence false\nlog_type all\nlog_timestamp_format %H:%M:%S\n"
        )
        self.log = open(tmp / "mosquitto.log", "w")
        self.proc = subprocess.Popen(
            ["mosquitto", "-c", str(conf)], stdout=self.log, stderr=subprocess.STDOUT
        )
        wait_for("mosquitto listening", self.listening, 10)

    def listening(self):
        try:
            socket.create_connection(("127.0.0.1", self.port), 0.5).close()
            return True
        except OSError:
            return False

    def stop(self):
        self.proc.terminate()
        self.proc.wait(10)


class Watch:
    """Every message on the broker, with its arrival time."""

    def __init__(self, port):
        self.lock = threading.Lock()
        self.messages = []
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="tinybms-ha-check")
        c.on_message = self._on
        c.on_connect = lambda cl, *_: cl.subscribe("#")
        c.connect("127.0.0.1", port)
        c.loop_start()
        self.client = c

    def _on(self, _c, _u, m):
        with self.lock:
            self.messages.append((time.monotonic(), m.topic, bytes(m.payload)))

    def last(self, topic):
        with self.lock:
            for t, top, p in reversed(self.messages):
                if top == topic:
                    return t, p
        return None

    def last_with(self, topic, payload):
        """When `payload` last arrived on `topic` (None: never)."""
        with self.lock:
            for t, top, p in reversed(self.messages):
                if top == topic and p == payload:
                    return t
        return None

    def serials_since(self, since, prefix="tinybms"):
        """Serials that published a state since `since`."""
        with self.lock:
            tops = {top for t, top, _ in self.messages if t >= since}
        return sorted(
            t.split("/")[1] for t in tops if re.fullmatch(prefix + r"/[0-9A-F]{24}/state", t)
        )

    def stop(self):
        self.client.loop_stop()
        self.client.disconnect()


class Sim:
    """One `sim` process (a simulated bridge publishing to the broker)."""

    def __init__(self, sim, tmp, name, args):
        self.log = open(tmp / f"sim-{name}.log", "w")
        self.proc = subprocess.Popen(
            [sim, *args], stdout=self.log, stderr=subprocess.STDOUT
        )
        self.path = tmp / f"sim-{name}.log"

    def signal(self, sig):
        self.proc.send_signal(sig)

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.kill()
        self.proc.wait(10)
        self.log.close()

    def text(self):
        return self.path.read_text()


class HomeAssistant:
    def __init__(self, tmp, broker_port):
        self.dir = tmp / "config"
        self.dir.mkdir()
        self.port = free_port()
        self.log = tmp / "home-assistant.log"
        (self.dir / "configuration.yaml").write_text(
            "homeassistant:\n  name: tinybms-check\n  latitude: 0\n  longitude: 0\n"
            "  elevation: 0\n  unit_system: metric\n  time_zone: UTC\n"
            "  currency: EUR\n  country: DE\n"
            f"http:\n  server_host: 127.0.0.1\n  server_port: {self.port}\n"
            "api:\nconfig:\nenergy:\n"
            f"recorder:\n  db_url: sqlite:///{tmp / 'recorder.db'}\n  commit_interval: 1\n"
            "logger:\n  default: warning\n"
        )
        self.token = asyncio.run(self._make_token())
        self.broker_port = broker_port
        self.proc = None
        self.start()

    async def _make_token(self):
        # A user and a long-lived access token, made with Home Assistant's own
        # auth manager before it runs (what the UI's profile page does).
        from homeassistant import auth, core
        from homeassistant.auth.const import GROUP_ID_ADMIN
        from homeassistant.auth.models import TOKEN_TYPE_LONG_LIVED_ACCESS_TOKEN

        hass = core.HomeAssistant(str(self.dir))
        hass.auth = await auth.auth_manager_from_config(hass, [{"type": "homeassistant"}], [])
        user = await hass.auth.async_create_user("tinybms-check", group_ids=[GROUP_ID_ADMIN])
        refresh = await hass.auth.async_create_refresh_token(
            user,
            client_name="tinybms-check",
            token_type=TOKEN_TYPE_LONG_LIVED_ACCESS_TOKEN,
            access_token_expiration=timedelta(days=30),
        )
        token = hass.auth.async_create_access_token(refresh)
        await hass.async_stop(force=True)
        return token

    def start(self):
        hass = Path(sys.executable).parent / "hass"
        self.out = open(self.log.with_suffix(".out"), "a")
        t0 = time.monotonic()
        self.proc = subprocess.Popen(
            [str(hass), "-c", str(self.dir), "--skip-pip", "--log-file", str(self.log)],
            stdout=self.out,
            stderr=subprocess.STDOUT,
        )
        try:
            wait_for("Home Assistant's API", self._api_up, 120, 0.5)
        except Failed:
            self.proc.kill()
            self.proc.wait(10)
            raise
        self.started_in = time.monotonic() - t0

    def _api_up(self):
        check(self.proc.poll() is None, "Home Assistant exited")
        try:
            return self.get("/api/config").get("state") == "RUNNING"
        except OSError:
            return False

    def stop(self):
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.out.close()

    def request(self, method, path, body=None):
        req = urllib.request.Request(
            f"http://127.0.0.1:{self.port}{path}",
            method=method,
            data=None if body is None else json.dumps(body).encode(),
            headers={
                "Authorization": f"Bearer {self.token}",
                "Content-Type": "application/json",
            },
        )
        with urllib.request.urlopen(req, timeout=10) as r:
            return json.loads(r.read() or b"null")

    def get(self, path):
        return self.request("GET", path)

    def setup_mqtt(self):
        """The MQTT integration's config entry, through its config flow."""
        flow = self.request("POST", "/api/config/config_entries/flow", {"handler": "mqtt"})
        check(flow.get("step_id") == "broker", f"MQTT flow: {flow}")
        done = self.request(
            "POST",
            f"/api/config/config_entries/flow/{flow['flow_id']}",
            {"broker": "127.0.0.1", "port": self.broker_port},
        )
        check(done.get("type") == "create_entry", f"MQTT flow: {done}")

    def states(self):
        return {s["entity_id"]: s for s in self.get("/api/states")}

    def ws(self, *messages):
        """WebSocket API commands, in order; their results."""

        async def run():
            url = f"http://127.0.0.1:{self.port}/api/websocket"
            timeout = aiohttp.ClientTimeout(total=60)
            async with aiohttp.ClientSession(timeout=timeout) as s, s.ws_connect(url) as w:
                await asyncio.wait_for(w.receive_json(), 10)
                await w.send_json({"type": "auth", "access_token": self.token})
                auth = await asyncio.wait_for(w.receive_json(), 10)
                check(auth["type"] == "auth_ok", "WebSocket auth")
                out = []
                for i, m in enumerate(messages, 1):
                    await w.send_json({"id": i, **m})
                    while True:
                        r = await asyncio.wait_for(w.receive_json(), 10)
                        if r.get("id") == i and r.get("type") == "result":
                            break
                    check(r.get("success"), f"{m['type']}: {r}")
                    out.append(r["result"])
                return out

        return asyncio.run(run())

    def entities(self):
        """The entity registry: unique_id -> entry (MQTT's)."""
        (entries,) = self.ws({"type": "config/entity_registry/list"})
        return {e["unique_id"]: e for e in entries if e["platform"] == "mqtt"}

    def devices(self):
        (devs,) = self.ws({"type": "config/device_registry/list"})
        return devs

    def log_lines(self):
        return self.log.read_text(errors="replace").splitlines() if self.log.exists() else []


def serial_of(watch, prefix="tinybms"):
    """Serials that published a state."""
    with watch.lock:
        tops = {t for _, t, _ in watch.messages}
    return sorted(
        t.split("/")[1] for t in tops if re.fullmatch(prefix + r"/[0-9A-F]{24}/state", t)
    )


def expected_value(row, state):
    """What Home Assistant should show for a guide row, from the state JSON."""
    obj, _, platform, _, _, _, member = row
    m = re.match(r"(\w+)(\[(\d+)\])?", member)
    key = m.group(1)
    v = state.get(key)
    if m.group(3) is not None:
        v = v[int(m.group(3))]
    if platform == "binary_sensor":
        if v is None:
            return "unavailable"
        on = v > 0 if "> 0" in member else bool(v)
        return "on" if on else "off"
    if platform == "update":
        # No newer version seen: unknown, never "up to date" without knowing.
        if v is None:
            return "unavailable"
        return "unknown" if state.get("update_latest") is None else "on"
    if v is None:
        return "unavailable"
    return v


def same(ha, want):
    if want == "unavailable" or isinstance(want, str):
        return ha == want
    try:
        return abs(float(ha) - float(want)) < 1e-9
    except ValueError:
        return False


def check_entities(ha, watch, serial, pack_rows, figures):
    """Every guide row exists as documented, with the published value."""
    entities = wait_for(
        "every entity of the guide in Home Assistant",
        lambda: (lambda e: e if all(f"tinybms_{serial}_{r[0]}" in e for r in pack_rows) else None)(
            ha.entities()
        ),
        60,
        1.0,
    )
    devices = {d["id"]: d for d in ha.devices()}
    states = ha.states()
    device_ids = set()
    for row in pack_rows:
        obj, name, platform, dc, sc, unit, member = row
        e = entities[f"tinybms_{serial}_{obj}"]
        check(e["entity_id"].startswith(platform + "."), f"{obj}: {e['entity_id']}")
        device_ids.add(e["device_id"])
        s = states.get(e["entity_id"])
        check(s is not None, f"{obj}: no state")
        a = s["attributes"]
        want = lambda x: None if x == "—" else x  # noqa: E731
        check(a.get("device_class") == want(dc), f"{obj}: device class {a.get('device_class')}")
        check(a.get("state_class") == want(sc), f"{obj}: state class {a.get('state_class')}")
        check(
            a.get("unit_of_measurement") == want(unit),
            f"{obj}: unit {a.get('unit_of_measurement')}",
        )
        diagnostic = "diagnostic" in member
        check(
            e.get("entity_category") == ("diagnostic" if diagnostic else None),
            f"{obj}: category {e.get('entity_category')}",
        )
    check(len(device_ids) == 1, f"{len(device_ids)} devices for one BMS")
    dev = devices[device_ids.pop()]
    check(dev["name"] == f"TinyBMS {serial[-6:]}", f"device name {dev['name']}")
    check(dev["serial_number"] == serial, f"device serial {dev['serial_number']}")
    figures["entities"] = len(pack_rows)
    return entities


def compare_values(ha, entities, serial, pack_rows, last_state):
    states = ha.states()
    wrong = []
    compared = 0
    for row in pack_rows:
        if row[2] == "event":
            continue
        e = entities[f"tinybms_{serial}_{row[0]}"]
        got = states[e["entity_id"]]["state"]
        want = expected_value(row, last_state)
        if row[2] == "update":
            # The versions it shows are the bridge's firmware as published.
            a = states[e["entity_id"]]["attributes"]
            for k, member in (("installed_version", "bridge_firmware"),
                              ("latest_version", "update_latest")):
                if a.get(k) != last_state.get(member):
                    wrong.append(f"{row[0]}: {k} {a.get(k)!r}, published "
                                 f"{member} {last_state.get(member)!r}")
        compared += 1
        if not same(got, want):
            wrong.append(f"{row[0]}: Home Assistant {got!r}, published {want!r}")
    check(not wrong, "values differ:\n  " + "\n  ".join(wrong))
    return compared


def entities_of(ha, serial, obj):
    """The entity id of a pack's object."""
    return ha.entities()[f"tinybms_{serial}_{obj}"]["entity_id"]


def may_be_unavailable(entity_id):
    """Entities unavailable by design while their value is absent: an
    external temperature sensor a pack may not have (the simulated packs of
    some seeds have none), the event entity until a first event, and what
    stops charging or discharging, which only a 48 V hybrid inverter's
    protocol reports (null with Victron, the simulator's default), an
    inverter that ignored a stop (null while none has), the measured capacity
    (null until a run from full to the knee qualified) and the spread at the
    top of charge (null until a whole day closed)."""
    return (
        "_temperature_" in entity_id
        or entity_id.startswith("event.")
        or entity_id.endswith(
            (
                "_stopped_by",
                "_charge_stop",
                "_discharge_stop",
                "_inverter_ignored_a_stop",
                "_measured_capacity",
                "_spread_at_the_top_of_charge",
            )
        )
    )


def ours(states, serial):
    return {k: v for k, v in states.items() if f"tinybms_{serial[-6:].lower()}_" in k}


def main():
    sim_bin = os.path.abspath(sys.argv[1])
    tmp = Path(tempfile.mkdtemp(prefix="tinybms-ha-"))
    t_start = time.monotonic()
    figures = {}
    pack_rows, battery_rows = guide_tables()
    sims = []
    broker = watch = ha = None

    def sim(name, *args):
        s = Sim(sim_bin, tmp, name, ["--mqtt", f"127.0.0.1:{broker.port}", *args])
        sims.append(s)
        return s

    try:
        broker = Broker(tmp)
        watch = Watch(broker.port)
        ha = HomeAssistant(tmp, broker.port)
        figures["home assistant start"] = f"{ha.started_in:.1f} s"
        ha.setup_mqtt()
        # 1. Every documented entity, as documented.
        a = sim("a", "--seed", "1")
        serial = wait_for("a state from the bridge", lambda: serial_of(watch), 30)[0]
        state_topic = f"tinybms/{serial}/state"
        entities = check_entities(ha, watch, serial, pack_rows, figures)
        print(f"ok: {len(pack_rows)} documented entities, one device TinyBMS {serial[-6:]}")

        # Wait for a state after all configs, so every entity has a value.
        time.sleep(6)

        # 2. A hung bridge: stopped, its connection left open.
        missing = []

        def all_available(ser=serial):
            s = ours(ha.states(), ser)
            missing[:] = sorted(
                k for k, v in s.items() if v["state"] == "unavailable" and not may_be_unavailable(k)
            )
            return s and not missing

        def still_missing():
            return "unavailable: " + ", ".join(missing)

        def hang(override_will, while_hung=None):
            """Stops the bridge (`while_hung` gets its last state 1 s later);
            the time from its last state until every entity (every entity but
            the event, with `override_will`) is unavailable."""
            a.signal(signal.SIGSTOP)
            time.sleep(1.0)
            last_at, last_payload = watch.last(state_topic)
            if while_hung:
                while_hung(json.loads(last_payload))
            avail = f"tinybms/{serial}/availability"
            first_gone = {}

            def gone():
                if override_will:
                    # A broker that never notices the silent connection: the
                    # availability stays `online`, only the expiry is left.
                    # A reading soon after the will (before Home Assistant has
                    # our `online` again) says nothing about the expiry.
                    watch.client.publish(avail, "online", retain=True)
                    will = watch.last_with(avail, b"offline")
                    if will is not None and will > last_at and time.monotonic() - will < 2.0:
                        return False
                s = ours(ha.states(), serial)
                seen = {k: time.monotonic() for k, v in s.items() if v["state"] == "unavailable"}
                live = [
                    k
                    for k, v in s.items()
                    if v["state"] != "unavailable"
                    # The event and the firmware's update entity have no
                    # expiry (Home Assistant's MQTT event and update take
                    # none): only the will makes them unavailable.
                    and not (override_will and k.startswith(("event.", "update.")))
                ]
                done = not live and len(s) >= len(pack_rows)
                if override_will and seen:
                    # Home Assistant may read the will before this watcher
                    # has it (both get it from the broker at once): look
                    # again a moment later, and a reading the will explains
                    # counts for nothing.
                    time.sleep(0.5)
                    will = watch.last_with(avail, b"offline")
                    if will is not None and will > last_at and time.monotonic() - will < 2.5:
                        return False
                for k, at in seen.items():
                    first_gone.setdefault(k, at)
                return done

            wait_for("a hung bridge's entities unavailable", gone, EXPIRE_S + 30)
            t = time.monotonic() - last_at
            first = min(first_gone.values()) - last_at
            if override_will:
                # Leave the will's word on the broker for what follows.
                watch.client.publish(avail, "offline", retain=True)
            a.signal(signal.SIGCONT)
            return t, first, last_at

        def values_equal(last_state):
            n = compare_values(ha, entities, serial, pack_rows, last_state)
            print(f"ok: {n} values equal what the bridge published")

        # The update entity's template as published, rendered by Home
        # Assistant itself: a latest version only when the bridge knows one
        # (a null one makes Home Assistant drop the whole message).
        with watch.lock:
            update_configs = [
                json.loads(p)
                for _, top, p in watch.messages
                if top.startswith("homeassistant/update/") and top.endswith("/config") and p
            ]
        check(update_configs, "no update entity's config published")
        template = update_configs[-1]["value_template"]
        for latest in (None, "9.9.9"):
            got = ha.request("POST", "/api/template", {
                "template": template,
                "variables": {"value_json": {
                    "bridge_firmware": "0.1.0", "update_latest": latest,
                    "update_rolled_back": None,
                }},
            })
            want = {"installed_version": "0.1.0", "release_summary": ""}
            if latest:
                want["latest_version"] = latest
            check(got == want, f"update template with update_latest {latest!r}: {got}")
        print("ok: the update entity names a latest version only when one is known")

        hung_expiry, first, _ = hang(True, values_equal)
        figures["hung bridge, expiry alone: first entity unavailable after"] = f"{first:.1f} s"
        figures["hung bridge, expiry alone: every entity unavailable after"] = (
            f"{hung_expiry:.1f} s"
        )
        check(
            EXPIRE_S - 1 <= hung_expiry <= EXPIRE_S + SLACK_S,
            f"by expiry alone unavailable after {hung_expiry:.1f} s, not {EXPIRE_S} s",
        )
        print(f"ok: by expiry alone unavailable {hung_expiry:.1f} s after the last state")
        back = time.monotonic()
        wait_for(
            "the bridge's entities back after it resumed", all_available, 90, 0.5, still_missing
        )
        figures["resumed bridge: back after"] = f"{time.monotonic() - back:.1f} s"
        time.sleep(6)
        hung, first, last_at = hang(False)
        will = watch.last(f"tinybms/{serial}/availability")
        if will and will[1] == b"offline" and will[0] > last_at:
            figures["hung bridge: the broker's will after the last state"] = (
                f"{will[0] - last_at:.1f} s"
            )
        figures["hung bridge: every entity unavailable after the last state"] = f"{hung:.1f} s"
        check(hung <= EXPIRE_S + SLACK_S, f"hung bridge unavailable after {hung:.1f} s")
        print(f"ok: hung bridge unavailable {hung:.1f} s after its last state (bound {EXPIRE_S} s)")
        wait_for(
            "the bridge's entities back after it resumed", all_available, 90, 0.5, still_missing
        )
        print("ok: back after the bridge resumed")

        # 3. A killed connection: unavailable at once (the will).
        def all_unavailable():
            s = ours(ha.states(), serial)
            return len(s) >= len(pack_rows) and all(
                v["state"] == "unavailable" for v in s.values()
            )

        a.signal(signal.SIGKILL)
        killed = time.monotonic()
        wait_for("a killed bridge's entities unavailable", all_unavailable, 30, 0.1)
        dt = time.monotonic() - killed
        figures["killed connection: unavailable after"] = f"{dt:.1f} s"
        check(dt <= KILLED_BOUND_S, f"killed connection unavailable after {dt:.1f} s")
        print(f"ok: killed connection unavailable after {dt:.1f} s")

        # 4. Home Assistant restarted: the entities come back.
        a = sim("a2", "--seed", "1")
        wait_for("the bridge back", all_available, 60, 0.5, still_missing)
        ha.stop()
        ha.start()
        restarted = time.monotonic()
        wait_for(
            "the entities after Home Assistant's restart", all_available, 60, 0.5, still_missing
        )
        figures["home assistant restarted: entities back after"] = (
            f"{time.monotonic() - restarted:.1f} s"
        )
        print("ok: entities back after Home Assistant restarted")

        # 5. The energy entities, by the Energy dashboard's own validation.
        charged = entities[f"tinybms_{serial}_energy_charged"]["entity_id"]
        discharged = entities[f"tinybms_{serial}_energy_discharged"]["entity_id"]
        _, validation = ha.ws(
            {
                "type": "energy/save_prefs",
                "energy_sources": [
                    {
                        "type": "battery",
                        "stat_energy_from": discharged,
                        "stat_energy_to": charged,
                    }
                ],
            },
            {"type": "energy/validate"},
        )
        # `statistics_not_defined` only says the recorder has not compiled
        # their first statistics yet (it does every 5 minutes): any other
        # issue (unit, device class, state class, value) is a failure.
        issues = [
            i
            for group in validation["energy_sources"]
            for i in group
            if i["type"] != "statistics_not_defined"
        ]
        check(not issues, f"the Energy dashboard's validation: {issues}")
        (stats,) = ha.ws({"type": "recorder/validate_statistics"})
        bad = {k: v for k, v in stats.items() if "tinybms" in k}
        check(not bad, f"the recorder's statistics validation: {bad}")
        print("ok: the Energy dashboard and the recorder accept the entities")

        # 6. Two bridges on one broker: two devices, neither disturbed.
        # The second bridge's BMS cuts off for over-temperature 12 s in, and
        # recovers only after this step: its event and status must show in
        # Home Assistant (during the sampling, or waited for after it).
        b = sim("b", "--seed", "2", "--bms-fault", "12s+300s")
        serials = wait_for("two bridges publishing", lambda: (lambda s: s if len(s) == 2 else None)(serial_of(watch)), 30)
        other = [s for s in serials if s != serial][0]
        check_entities(ha, watch, other, pack_rows, figures)
        wait_for(
            "both devices available", lambda: all_available() and all_available(other), 60, 0.5
        )
        flaps = {}
        event_id = entities_of(ha, other, "events")
        status_id = entities_of(ha, other, "status")
        fault_events, statuses = [], set()
        for _ in range(50):
            s = ha.states()
            for ser in (serial, other):
                for k, v in ours(s, ser).items():
                    if v["state"] == "unavailable" and not may_be_unavailable(k):
                        flaps[k] = flaps.get(k, 0) + 1
            ev = s.get(event_id, {}).get("attributes", {})
            if ev.get("event_type") == "fault":
                fault_events.append(ev)
            statuses.add(s.get(status_id, {}).get("state"))
            time.sleep(0.5)
        check(not flaps, f"unavailable readings with two bridges: {flaps}")

        def fault_seen():
            s = ha.states()
            ev = s.get(event_id, {}).get("attributes", {})
            statuses.add(s.get(status_id, {}).get("state"))
            if ev.get("event_type") == "fault":
                fault_events.append(ev)
            return fault_events and "Fault" in statuses

        wait_for(f"the fault in Home Assistant (statuses seen: {statuses})", fault_seen, 60, 0.5)
        ev = fault_events[0]
        check("Temperature" in ev.get("name", ""), f"the fault event: {ev}")
        check(isinstance(ev.get("id"), int) and isinstance(ev.get("timestamp_s"), int), f"{ev}")
        check("Fault" in statuses, f"the status never showed Fault: {statuses}")
        print(f"ok: the BMS's fault reached Home Assistant: event {ev['name']!r}, status Fault")
        for s in (a, b):
            check("connection lost" not in s.text(), f"a bridge lost its connection:\n{s.text()}")
        print(f"ok: two bridges, two devices ({serial[-6:]}, {other[-6:]}), 25 s without a flap")
        b.stop()

        # 7. Discovery off: the entities and the device are removed.
        a.stop()
        a = sim("a3", "--seed", "1", "--config", "discovery=off")

        def gone():
            e = ha.entities()
            left = [u for u in e if u.startswith(f"tinybms_{serial}_")]
            devs = [d for d in ha.devices() if d["name"] == f"TinyBMS {serial[-6:]}"]
            return not left and not devs and not ours(ha.states(), serial)

        wait_for("entities and device removed with discovery off", gone, 30, 0.5)
        print("ok: discovery off removes the entities and the device")
        a.stop()

        # 8. Several packs: each pack's device and the battery's.
        packs_from = time.monotonic()
        p = sim("packs", "--packs", "3")
        battery_ids = [f"tinybms_battery_tinybms_{r[0]}" for r in battery_rows]

        def battery_there():
            e = ha.entities()
            return e if all(u in e for u in battery_ids) else None

        e = wait_for("the battery's device", battery_there, 60, 1.0)
        states = ha.states()
        for r in battery_rows:
            obj, _, platform, dc, sc, unit, _ = r
            s = states[e[f"tinybms_battery_tinybms_{obj}"]["entity_id"]]
            want = lambda x: None if x == "—" else x  # noqa: E731
            a_ = s["attributes"]
            check(a_.get("device_class") == want(dc), f"battery {obj}: {a_}")
            check(a_.get("state_class") == want(sc), f"battery {obj}: {a_}")
            check(a_.get("unit_of_measurement") == want(unit), f"battery {obj}: {a_}")
        wait_for(
            "the battery's values",
            lambda: all(
                ha.states()[e[u]["entity_id"]]["state"] not in ("unavailable", "unknown")
                for u in battery_ids
            ),
            60,
            1.0,
        )
        pack_serials = wait_for(
            "three packs publishing",
            lambda: (lambda x: x if len(x) == 3 else None)(watch.serials_since(packs_from)),
            60,
        )
        names = {d["name"] for d in ha.devices()}
        packs = [ser for ser in pack_serials if f"TinyBMS {ser[-6:]}" in names]
        check(len(packs) == 3, f"pack devices {packs} of {pack_serials}")
        print(f"ok: the battery's {len(battery_rows)} entities and {len(packs)} pack devices")
        p.stop()

        # 9. Home Assistant's log: nothing about these entities.
        bad = [
            l
            for l in ha.log_lines()
            if re.search(r"\b(WARNING|ERROR|CRITICAL)\b", l)
            and re.search(r"tinybms|mqtt", l, re.I)
        ]
        check(not bad, "Home Assistant's log:\n" + "\n".join(bad))
        print("ok: no warning or error about them in Home Assistant's log")
    except Failed as f:
        print(f"FAIL: {f}")
        print(f"(logs in {tmp})")
        return 1
    finally:
        for s in sims:
            s.stop()
        for part in (ha, watch, broker):
            if part is not None:
                part.stop()
    figures["whole check"] = f"{time.monotonic() - t_start:.0f} s"
    print("--- figures ---")
    for k, v in figures.items():
        print(f"{k}: {v}")
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

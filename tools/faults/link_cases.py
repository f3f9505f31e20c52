"""The fault suite's cases that attack the MAVLink side: floods, forged clocks, impostor autopilots,
strangers on the port, forged and replayed signatures."""

from __future__ import annotations

import hashlib
import socket
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from mavvo.service.daemon import Daemon
from mavvo.service.link import Link
from mavvo.service.link_options import LinkOptions
from mavvo.service.mavlink import mavutil
from mavvo.service.timing import MonotonicClock
from mavvo.sim.scenarios.service_run import run_daemon_in_sim
from tools.faults.harness import (
    SIGNING_EPOCH_UNIX_S,
    FaultRow,
    Outcome,
    attitude_bytes,
    flow_outcome,
    heartbeat_bytes,
    hover,
    longest_gap_s,
    lost,
)

__all__ = ["forged_clock", "foreign_sender_udpout", "impostor_heartbeat", "signing_forgery_and_replay", "udp_flood"]


def udp_flood(tmp: Path) -> FaultRow:
    """20 000 garbage datagrams a second for 10 s at the port the service listens on."""
    sent = Counter[str]()

    def flood(daemon: Daemon, address: tuple[str, int]) -> None:
        rng = np.random.default_rng(3)
        garbage = [bytes(rng.integers(0, 256, 64, dtype=np.uint8)) for _ in range(200)]
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setblocking(False)
        time.sleep(5.0)  # the flight controller is chosen and estimates flow by then
        t0 = time.monotonic()
        while (t := time.monotonic() - t0) < 10.0 and not daemon.stop_event.is_set():
            for g in garbage:  # 200 per 10 ms
                try:
                    s.sendto(g, address)
                    sent["datagrams"] += 1
                except OSError:
                    sent["refused"] += 1
            time.sleep(max(0.0, 0.01 * (int(t / 0.01) + 1) - (time.monotonic() - t0)))
        s.close()

    run = run_daemon_in_sim(hover(20.0), realtime=True, service_listens=True, during=flood)
    gap = longest_gap_s(run)
    c = run.daemon.counters
    return FaultRow(
        "20k garbage datagrams/s for 10 s on the service's UDP port",
        flow_outcome(run, gap),
        gap,
        lost(c, "link_stale_dropped", "skipped_attitude_stale", "skipped_attitude_missing"),
        f"{sent['datagrams']} sent, {c.get('link_bad_data', 0)} read as bad data, {run.received.get('HEARTBEAT', 0)} HEARTBEATs sent",
    )


def forged_clock(tmp: Path) -> FaultRow:
    """A forged TIMESYNC answer, an ATTITUDE stamped 1 s ahead and one 5 ms ahead, from another sender."""

    def forge(daemon: Daemon, address: tuple[str, int]) -> None:
        m = mavutil().mavlink
        mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        time.sleep(6.0)
        boot_ms = int(daemon.clock.now_s() * 1000)  # about the flight controller's boot clock in the simulator
        now_ns = int(daemon.clock.now_s() * 1e9)
        s.sendto(bytes(m.MAVLink_timesync_message(now_ns + 10**9, now_ns - 10**6).pack(mav)), address)
        s.sendto(attitude_bytes(mav, boot_ms + 1000, roll=0.9), address)
        s.sendto(attitude_bytes(mav, boot_ms + 5, roll=0.9), address)
        s.close()

    run = run_daemon_in_sim(hover(16.0), realtime=True, service_listens=True, during=forge)
    gap = longest_gap_s(run)
    c = run.daemon.counters
    return FaultRow(
        "forged TIMESYNC answer; ATTITUDE stamped 1 s and 5 ms ahead",
        flow_outcome(run, gap),
        gap,
        lost(c, "fc_attitude_implausible", "fc_timesync_implausible", "skipped_attitude_wait"),
        "dropped by the sender filter (the flight controller's address is pinned); the plausibility checks behind it are tested alone",
    )


def impostor_heartbeat(tmp: Path) -> FaultRow:
    """HEARTBEATs from another system id before (and while) the real flight controller's come (before:
    the first one was followed for the whole run, 0 of 700 genuine ATTITUDE accepted)."""
    seen: dict[str, int | None] = {}

    def impostor(daemon: Daemon, address: tuple[str, int]) -> None:
        mav = mavutil().mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        daemon.link.connected.wait(30)  # the service's socket exists
        sent = 0
        while daemon.link.fc_component_id is None and not daemon.stop_event.is_set():
            s.sendto(heartbeat_bytes(mav), address)
            sent += 1
            time.sleep(0.01)
        s.close()
        seen["system"], seen["sent"] = daemon.link.fc_system_id, sent

    run = run_daemon_in_sim(hover(8.0), service_listens=True, during=impostor)  # lockstep
    gap = longest_gap_s(run)
    c = run.daemon.counters
    ok = flow_outcome(run, gap) is Outcome.SURVIVED and seen.get("system") == 1 and (seen.get("sent") or 0) > 0
    return FaultRow(
        "HEARTBEATs from another system id before the flight controller's",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        gap,
        lost(c, "skipped_attitude_missing"),
        f"{seen.get('sent')} impostor HEARTBEATs; followed system {seen.get('system')}; {c.get('fc_attitude', 0)} ATTITUDE accepted",
    )


def foreign_sender_udpout(tmp: Path) -> FaultRow:
    """``udpout``: datagrams from another sender than the flight controller (before: accepted from anyone)."""
    seen: dict[str, object] = {}

    def stranger(daemon: Daemon, address: tuple[str, int]) -> None:
        mav = mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        seen["bound_to"] = address[0]
        sent = 0
        for i in range(2000):
            sent += s.sendto(b"\x00garbage" if i % 2 else attitude_bytes(mav, 10**6 + i, roll=0.9), address) > 0
        seen["sent"] = sent
        s.close()

    run = run_daemon_in_sim(hover(10.0), during=stranger)
    gap = longest_gap_s(run)
    c = run.daemon.counters
    ok = (
        flow_outcome(run, gap) is Outcome.SURVIVED
        and c.get("link_bad_data", 0) == 0
        and seen.get("bound_to") == "127.0.0.1"
        and seen.get("sent") == 2000
    )
    return FaultRow(
        "udpout: 2000 datagrams from a stranger",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        gap,
        lost(c, "link_bad_data", "fc_attitude_implausible"),
        f"{seen.get('sent')} sent to {seen.get('bound_to')}, none read (the socket is connected to the flight controller)",
    )


def signing_forgery_and_replay(tmp: Path) -> FaultRow:
    """Signing on: one frame with a wrong signature and a huge timestamp, then a genuine frame from
    another link id 5 s old with a boot time 60 s back (before: genuine traffic refused for 3.3 s; the
    replay faked a reboot)."""
    key_file = tmp / "signing.key"
    key_file.write_text("a passphrase\n")
    key_file.chmod(0o600)
    key = hashlib.sha256(b"a passphrase").digest()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    got: list[int] = []

    class Listener:
        def on_attitude(self, t_fc_ms, *args, **kw):
            got.append(t_fc_ms)

        def __getattr__(self, name):
            return lambda *a, **k: None

    link = Link(
        LinkOptions(url=f"udpin:127.0.0.1:{port}", signing_key_file=str(key_file), fc_system_id=1),
        MonotonicClock(),
        Listener(),
    )
    stop = threading.Event()
    t = threading.Thread(target=link.run, args=(stop,), daemon=True)
    t.start()

    def signer(link_id: int, timestamp: int):
        mav = mavutil().mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id, mav.signing.timestamp = (
            key,
            True,
            link_id,
            timestamp,
        )
        return mav

    fc = signer(0, int((time.time() - SIGNING_EPOCH_UNIX_S) * 100_000))
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        link.connected.wait(30)
        s.sendto(heartbeat_bytes(fc), ("127.0.0.1", port))
        boot_ms = 100_000
        genuine = 0
        for i in range(40):
            if i == 20:
                forged = bytearray(attitude_bytes(fc, boot_ms + 5))
                forged[-12:-6] = (2**47).to_bytes(6, "little")  # far ahead; the signature no longer matches
                s.sendto(bytes(forged), ("127.0.0.1", port))
            boot_ms += 10
            s.sendto(attitude_bytes(fc, boot_ms), ("127.0.0.1", port))
            genuine += 1
        s.sendto(attitude_bytes(signer(1, fc.signing.timestamp - 500_000), boot_ms - 60_000), ("127.0.0.1", port))
        boot_ms += 10
        s.sendto(attitude_bytes(fc, boot_ms), ("127.0.0.1", port))
        genuine += 1
        deadline = time.monotonic() + 30
        while len(got) < genuine and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        s.close()
        stop.set()
        t.join(10)
    c = link.counters
    ok = len(got) == genuine and c["signature_bad"] == 1 and c["signature_replayed"] == 1 and c["reboots"] == 0
    return FaultRow(
        "signing: a forged frame with a huge timestamp; a replay from another link id",
        Outcome.SURVIVED if ok else Outcome.FAILED,
        float("nan"),
        f"{genuine - len(got)} of {genuine} genuine frames",
        f"signature_bad {c['signature_bad']}, signature_replayed {c['signature_replayed']}, reboots {c['reboots']}",
    )

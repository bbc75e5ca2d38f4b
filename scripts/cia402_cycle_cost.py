"""Per-cycle cost of the CiA 402 driver against the simulated drives (docs/hardware.md, "Per-cycle cost").

For each setting (PDO with status on change, PDO with Elmo-like timer-only status, SDO only) it
runs a 50 Hz loop of ``positions()`` + ``send_setpoints()`` for both drives on python-can's virtual
bus and counts the CAN frames each cycle puts on the bus (RPDO, TPDO, SDO) and the time the
driver's calls take. Prints a Markdown table. Run: ``python scripts/cia402_cycle_cost.py``.
"""
from __future__ import annotations

import sys
import time
import uuid
from collections import Counter
from dataclasses import replace
from pathlib import Path

import can
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from targetlock.interfaces.canbus import CanBusConfig  # noqa: E402
from targetlock.interfaces.cia402 import CanopenDrives, CanopenRigConfig  # noqa: E402
from targetlock.interfaces.sim_cia402 import SimDriveBehaviour, SimDriveSet  # noqa: E402

CYCLES = 100
RATE_HZ = 50.0


def kind(arbitration_id: int) -> str:
    fn = arbitration_id & 0x780
    return {0x180: "TPDO", 0x200: "RPDO", 0x580: "SDO", 0x600: "SDO", 0x700: "heartbeat"}.get(fn, "other")


def measure(name: str, behaviour: SimDriveBehaviour, **cfg_over) -> dict:
    bus = CanBusConfig(interface="virtual", channel=f"cost-{uuid.uuid4().hex[:8]}")
    cfg = replace(CanopenRigConfig(bus=bus), status_timeout=0.3, heartbeat_timeout=0.5, sdo_timeout=0.5, **cfg_over)
    counts: Counter = Counter()
    with SimDriveSet(bus, cfg.node_ids, cfg.drive_params(), behaviour=behaviour):
        with CanopenDrives(cfg) as drives:
            drives.home()
            spy = can.Bus(interface="virtual", channel=bus.channel)
            calls = []
            try:
                next_t = time.monotonic()
                for k in range(CYCLES):
                    next_t += 1.0 / RATE_HZ
                    time.sleep(max(0.0, next_t - time.monotonic()))
                    t0 = time.perf_counter()
                    drives.positions()
                    drives.send_setpoints(np.array([20 * k, -20 * k]))
                    calls.append(time.perf_counter() - t0)
                while (msg := spy.recv(0.0)) is not None:
                    counts[kind(msg.arbitration_id)] += 1
            finally:
                spy.shutdown()
            r = drives.report()
    ms = np.array(calls) * 1e3
    return {"name": name, **{k: counts[k] / CYCLES for k in ("RPDO", "TPDO", "SDO")},
            "p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)), "max": float(ms.max()),
            "missed": r["missed"]}


def main() -> None:
    rows = [
        measure("PDO, status on change + 5 ms timer", SimDriveBehaviour()),
        measure("PDO, status on 5 ms timer only (Elmo default), strict handshake",
                SimDriveBehaviour(strict_setpoint=True, status_on_change=False)),
        measure("SDO only", SimDriveBehaviour(), use_pdo=False),
    ]
    print("| setting | RPDO / cycle | TPDO / cycle | SDO frames / cycle | call time p50 / p99 / max (ms) | missed |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['name']} | {r['RPDO']:.1f} | {r['TPDO']:.1f} | {r['SDO']:.1f} | "
              f"{r['p50']:.2f} / {r['p99']:.2f} / {r['max']:.2f} | {r['missed']} |")


if __name__ == "__main__":
    main()

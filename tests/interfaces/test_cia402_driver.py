"""The CiA 402 driver against simulated drives on python-can's virtual bus (one process)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from targetlock.interfaces import od402 as o
from targetlock.interfaces.cia402 import CanopenDrives
from targetlock.interfaces.errors import BusError, MotionRefused
from targetlock.interfaces.od402 import State, decode_state
from targetlock.rig.base import DriveFault

from iface_helpers import rig, wait_until


def move_and_settle(drives, target, timeout=1.5):
    drives.send_setpoints(np.array(target))
    ok = wait_until(lambda: np.all(np.abs(drives.positions() - np.array(target)) <= 25), timeout)
    return ok


def test_start_brings_both_drives_to_operation_enabled_with_pdos():
    with rig() as (cfg, sims, drives):
        assert drives.states() == [State.OPERATION_ENABLED, State.OPERATION_ENABLED]
        assert [s.nmt_state for s in sims.drives] == ["OPERATIONAL", "OPERATIONAL"]
        assert drives.fault() is None and not drives.homed
        # TPDO1 streams statusword + position on its event timer
        assert wait_until(lambda: all(d.tpdo_count > 5 for d in drives.drives), 1.0)
        sim = sims[cfg.node_ids[0]]
        assert sim._tpdos[0].mapped() == [(o.STATUSWORD, 0, 16), (o.POSITION_ACTUAL, 0, 32)]
        assert sim._rpdos[0].mapped() == [(o.CONTROLWORD, 0, 16), (o.TARGET_POSITION, 0, 32)]
        assert sim._params_od[(o.PRODUCER_HEARTBEAT, 0)] == round(cfg.heartbeat_period * 1e3)
        assert sim._params_od[(o.PROFILE_VELOCITY, 0)] == cfg.ticks(cfg.profile_velocity)


def test_state_machine_disable_and_explicit_enable():
    with rig() as (cfg, sims, drives):
        drives.disable()
        assert [d.state for d in sims.drives] == [State.SWITCH_ON_DISABLED] * 2
        assert drives.is_disabled() is True            # what a stopped run reports as "confirmed"
        drives.enable()
        assert drives.states() == [State.OPERATION_ENABLED] * 2
        assert drives.is_disabled() is False


def test_no_motion_before_homing():
    with rig() as (cfg, sims, drives):
        with pytest.raises(MotionRefused, match="not homed"):
            drives.send_setpoints(np.array([1000, 1000]))
        time.sleep(0.05)
        assert all(s.stats["setpoints"] == 0 for s in sims.drives)
        assert all(s.stats["rpdo"] == 0 for s in sims.drives)


def test_homing_with_motion_declares_zero_at_neutral():
    with rig(initial_angles=(0.05, -0.03), encoder_offsets=(5000, -7000), homing_method=21) as (cfg, sims, drives):
        before = drives.positions()
        assert before.tolist() == [round(0.05 / cfg.rad_per_tick) + 5000, round(-0.03 / cfg.rad_per_tick) - 7000]
        t0 = time.monotonic()
        drives.home()
        took = time.monotonic() - t0
        assert drives.homed
        # the homing motion runs at the homing speed (0.32 rad/s): 0.05 rad take >= 0.15 s
        assert took > 0.05 / cfg.homing_speed * 0.9
        assert np.all(np.abs(sims.angles()) < 4e-4)
        assert np.all(np.abs(drives.positions()) <= 25)
        assert all(s.homed for s in sims.drives)
        # software limits written after homing, in the homed frame
        assert sims[cfg.node_ids[0]]._params_od[(o.SOFTWARE_LIMITS, 2)] == cfg.max_ticks


def test_homing_on_current_position_does_not_move():
    with rig(initial_angles=(0.02, 0.01), encoder_offsets=(123, 456), homing_method=37) as (cfg, sims, drives):
        drives.home()
        assert drives.positions().tolist() == [0, 0]
        assert np.allclose(sims.angles(), [0.02, 0.01])


def test_homing_error_is_a_drive_fault():
    with rig(homing_method=0) as (cfg, sims, drives):
        with pytest.raises(DriveFault, match="homing error"):
            drives.home()
        assert not drives.homed


def test_moves_reach_the_setpoint_at_the_drive_models_rate():
    with rig() as (cfg, sims, drives):
        drives.home()
        target = np.array([20000, -12000])     # 0.32 rad and -0.19 rad
        t0 = time.monotonic()
        drives.send_setpoints(target)
        time.sleep(0.1)
        mid = drives.positions()
        elapsed = time.monotonic() - t0
        # rate limit of the drive model: at most 100000 tick/s
        assert np.all(np.abs(mid) <= cfg.ticks(cfg.profile_velocity) * (elapsed + 0.01) + 30)
        assert abs(mid[0]) > 3000            # but it is moving
        assert wait_until(lambda: np.all(np.abs(drives.positions() - target) <= 25), 1.0)
        # The reported position is a PDO snapshot; the drive itself settles within the same tolerance.
        assert wait_until(lambda: np.allclose(sims.angles(), target * cfg.rad_per_tick, atol=4e-4), 1.0)
        assert all(s.stats["setpoints"] == 1 for s in sims.drives)


def test_setpoints_are_clamped_to_the_limits():
    with rig(min_angle=-0.1, max_angle=0.1) as (cfg, sims, drives):
        drives.home()
        drives.send_setpoints(np.array([10**7, -10**7]))
        lo, hi = drives.limits
        assert sims[cfg.node_ids[0]]._target_active == hi[0] == cfg.max_ticks
        assert sims[cfg.node_ids[1]]._target_active == lo[1] == cfg.min_ticks
        with pytest.raises(MotionRefused):
            drives.send_setpoints(np.array([np.nan, 0.0]))


def test_position_read_back_by_pdo():
    with rig() as (cfg, sims, drives):
        drives.home()
        assert move_and_settle(drives, [5000, -3000])
        time.sleep(0.25)                          # first-order tail: ~10 time constants until still
        n_sdo = drives.stats["sdo_position_reads"]
        pos = drives.positions()
        assert drives.stats["sdo_position_reads"] == n_sdo
        assert drives.stats["pdo_position_reads"] > 0
        assert pos.tolist() == [s.position_ticks for s in sims.drives]


def test_position_read_back_by_sdo_without_pdos():
    with rig(use_pdo=False) as (cfg, sims, drives):
        assert not any(d.pdo_active for d in drives.drives)
        assert not any(p.valid for s in sims.drives for p in s._tpdos + s._rpdos)
        drives.home()
        assert move_and_settle(drives, [-4000, 6000])
        time.sleep(0.25)
        assert drives.stats["sdo_position_reads"] > 0 and drives.stats["pdo_position_reads"] == 0
        assert drives.positions().tolist() == [s.position_ticks for s in sims.drives]
        assert all(s.stats["rpdo"] == 0 for s in sims.drives)


def test_stale_tpdo_falls_back_to_sdo():
    with rig() as (cfg, sims, drives):
        drives.home()
        sim = sims[cfg.node_ids[1]]
        sim._tpdos[0].event_timer_ms = 0          # the drive stops sending TPDO1 periodically
        time.sleep(drives.drives[1].pdo_stale_after + 0.02)
        n_sdo = drives.stats["sdo_position_reads"]
        assert drives.positions()[1] == sim.position_ticks
        assert drives.stats["sdo_position_reads"] == n_sdo + 1


def test_fault_injection_raises_and_needs_fault_reset_and_enable():
    with rig() as (cfg, sims, drives):
        drives.home()
        sims[cfg.node_ids[1]].inject_fault(0x2310)
        assert wait_until(lambda: drives.fault() is not None, 0.5)
        assert "0x2310" in drives.fault() and "over-current" in drives.fault()
        with pytest.raises(DriveFault, match="0x2310"):
            drives.send_setpoints(np.array([100, 100]))
        assert sims[cfg.node_ids[1]].state == State.FAULT
        drives.enable()                                  # fault reset + enable sequence
        assert drives.fault() is None
        assert drives.states() == [State.OPERATION_ENABLED] * 2
        assert move_and_settle(drives, [800, 800])


def test_persistent_fault_keeps_refusing_until_cleared():
    with rig() as (cfg, sims, drives):
        sim = sims[cfg.node_ids[0]]
        sim.inject_fault(0x5441, persistent=True)
        assert wait_until(lambda: drives.fault() is not None, 0.5)
        with pytest.raises(DriveFault):
            drives.enable()
        assert sim.state == State.FAULT
        sim.clear_fault()
        drives.enable()
        assert drives.fault() is None


def test_fault_without_emcy_reads_the_error_code():
    with rig() as (cfg, sims, drives):
        drives.home()
        sim = sims[cfg.node_ids[0]]
        sim.set_silent(True)           # the EMCY is lost ...
        sim.inject_fault(0x4310)
        sim.set_silent(False)          # ... but the statusword and 0x603F tell
        assert wait_until(lambda: drives.drives[0].statusword is not None
                          and drives.drives[0].statusword & o.SW_FAULT, 0.5)
        with pytest.raises(DriveFault, match="0x4310"):
            drives.send_setpoints(np.array([0, 0]))


def test_heartbeat_loss_is_detected_within_the_timeout():
    with rig(heartbeat_period=0.02, heartbeat_timeout=0.1) as (cfg, sims, drives):
        drives.home()
        t0 = time.monotonic()
        sims[cfg.node_ids[0]].stop_heartbeat()
        assert wait_until(lambda: drives.fault() is not None, 1.0, period=0.002)
        detected = time.monotonic() - t0
        assert "heartbeat lost" in drives.fault()
        # last heartbeat <= one period before the stop; monitor polls every 20 ms; scheduling margin
        assert detected <= cfg.heartbeat_timeout + 0.02 + 0.06
        assert detected >= cfg.heartbeat_timeout - cfg.heartbeat_period - 0.005
        with pytest.raises(DriveFault, match="heartbeat"):
            drives.send_setpoints(np.array([0, 0]))


def test_drive_leaving_operation_enabled_on_its_own_is_refused():
    with rig() as (cfg, sims, drives):
        drives.home()
        sim = sims[cfg.node_ids[0]]
        with sim._lock:
            sim._apply_controlword(o.CW_SWITCH_ON)        # e.g. someone disabled it from the drive's panel
            sim._after_change()
        assert wait_until(lambda: decode_state(drives.drives[0].statusword) == State.SWITCHED_ON, 0.5)
        # noticed from the status alone, without a set-point being sent
        assert "left operation enabled without a fault" in (drives.fault() or "")
        with pytest.raises(DriveFault, match="left operation enabled"):
            drives.send_setpoints(np.array([100, 100]))
        assert sim.stats["setpoints"] == 0
        drives.enable()
        assert move_and_settle(drives, [100, 100])


def test_silent_node_is_a_fault_and_commands_fail():
    with rig() as (cfg, sims, drives):
        drives.home()
        sims[cfg.node_ids[1]].set_silent(True)
        assert wait_until(lambda: drives.fault() is not None, 1.0)
        with pytest.raises(DriveFault):
            drives.send_setpoints(np.array([0, 0]))
        with pytest.raises(DriveFault):
            drives.enable()


# python-can's receive thread dies with the bus (its exception is what the driver reads, through
# Notifier.exception); pytest would otherwise print that thread's traceback as a warning.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_bus_loss_is_a_fault():
    with rig() as (cfg, sims, drives):
        drives.home()
        drives.network.bus.shutdown()          # the CAN interface goes away under the driver
        # the status PDOs stop: the driver reports it after status_timeout, without a command
        assert wait_until(lambda: drives.fault() is not None, cfg.status_timeout + 1.0)
        with pytest.raises(DriveFault):
            drives.send_setpoints(np.array([100, 0]))
        with pytest.raises(BusError):
            drives.drives[0].send_controlword(o.CW_ENABLE_OPERATION)


def test_rebooted_drive_loses_homing_and_is_reconfigured_on_enable():
    with rig() as (cfg, sims, drives):
        drives.home()
        sims[cfg.node_ids[0]].boot()            # power glitch: boot-up message, defaults restored
        assert wait_until(lambda: drives.fault() is not None, 0.5)
        assert "rebooted" in drives.fault()
        assert not drives.homed
        drives.enable()
        assert drives.fault() is None
        assert wait_until(lambda: drives.drives[0].tpdo_count > 0, 0.5)
        with pytest.raises(MotionRefused):
            drives.send_setpoints(np.array([0, 0]))
        drives.home()
        assert move_and_settle(drives, [300, 300])


def test_drive_faults_when_this_computer_stops_its_heartbeat():
    with rig(master_heartbeat_period=0.02, drive_consumer_timeout=0.1) as (cfg, sims, drives):
        drives.home()
        drives._master_hb.stop()                 # the host "dies" without disabling the drives
        assert wait_until(lambda: all(s.state == State.FAULT for s in sims.drives), 1.0)
        assert all(s._error_code == 0x8130 for s in sims.drives)
        assert wait_until(lambda: drives.fault() is not None and "0x8130" in drives.fault(), 0.5)


def test_close_leaves_the_drives_disabled():
    with rig(start_driver=False) as (cfg, sims, _):
        with CanopenDrives(cfg) as drives:
            drives.home()
            drives.send_setpoints(np.array([1000, 1000]))
        assert [s.state for s in sims.drives] == [State.SWITCH_ON_DISABLED] * 2
        assert [s.nmt_state for s in sims.drives] == ["PRE-OPERATIONAL"] * 2


def test_round_trip_times(record_property):
    """SDO and PDO round trips on the virtual bus (reported; loose upper bounds)."""
    with rig() as (cfg, sims, drives):
        drives.home()
        d = drives.drives[0]
        n = 200
        t0 = time.perf_counter()
        for _ in range(n):
            d.read(o.STATUSWORD)
        sdo = (time.perf_counter() - t0) / n
        t0 = time.perf_counter()
        for k in range(n):
            drives.send_setpoints(np.array([k, -k]))
        handshake = (time.perf_counter() - t0) / n
        record_property("sdo_upload_round_trip_s", sdo)
        record_property("pdo_setpoint_handshake_s", handshake)
        print(f"\nSDO upload round trip {sdo * 1e3:.3f} ms; PDO set-point handshake (2 axes) {handshake * 1e3:.3f} ms")
        assert sdo < 0.02 and handshake < 0.02
        assert drives.report()["missed"] <= n // 50     # back to back, a loaded machine may make a drive late

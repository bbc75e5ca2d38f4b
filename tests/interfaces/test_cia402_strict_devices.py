"""The CiA 402 driver against drives that behave like the independent devices of issue 10:
strict set-point handshake, status PDOs on a timer only, NMT pre-operational on a lost host
heartbeat, slow or hung SDO, "homing attained" kept from an earlier homing."""
from __future__ import annotations

import time
from dataclasses import replace

import canopen
import numpy as np
import pytest

from targetlock.config import ConfigError
from targetlock.interfaces import od402 as o
from targetlock.interfaces.cia402 import CanopenDrives, CanopenRigConfig
from targetlock.interfaces.od402 import State, sdo_abort_text
from targetlock.interfaces.safety import SafeDrives, SafetyConfig, SafetyTrip
from targetlock.interfaces.sim_cia402 import SimDriveBehaviour
from targetlock.rig.base import DriveFault

from iface_helpers import rig, wait_until

ELMO_LIKE = SimDriveBehaviour(strict_setpoint=True, status_on_change=False)
"""Strict handshake processed in the drive's cycle, status PDO on its 5 ms timer only."""
ROOMY = 0.03
"""Set-point call budget (s) for tests about counting, not timing: a loaded test machine can stall
the simulated drives' threads for longer than the 10 ms default."""


# ---------------------------------------------------------------- item 1: set-points lost silently

def test_strict_drive_takes_every_setpoint_the_driver_counts_as_sent():
    with rig(behaviour=ELMO_LIKE, setpoint_ack_timeout=ROOMY) as (cfg, sims, drives):
        drives.home()
        n = 30
        for k in range(n):
            drives.send_setpoints(np.array([100 * (k + 1), -100 * (k + 1)]))
            time.sleep(0.02)                                 # a 50 Hz loop
        r = drives.report()
        # every edge the driver sent was taken by the drives; none was ignored
        assert wait_until(lambda: sum(s.stats["setpoints"] for s in sims.drives) == r["edges"], 1.0)
        assert all(s.stats["ignored_edges"] == 0 for s in sims.drives)
        assert r["acked_in_call"] >= 2 * n - 4               # a loaded machine may make a drive late, rarely
        assert r["edges"] + r["missed"] >= 2 * n
        # the last set-point reached the drives
        assert wait_until(lambda: np.all(np.abs(drives.positions() - [100 * n, -100 * n]) <= 25), 2.0)


def test_setpoints_sent_back_to_back_are_never_silently_lost_on_a_strict_drive():
    """No pause between calls: the acknowledge of the previous set-point is still high at the next call.
    A strict drive with timer-only status takes at most one set-point per two status PDOs; the
    rest are counted missed, none is sent as an edge the drive ignores."""
    with rig(behaviour=ELMO_LIKE, setpoint_ack_timeout=ROOMY) as (cfg, sims, drives):
        drives.home()
        for k in range(20):
            try:
                drives.send_setpoints(np.array([50 * (k + 1), 0]))
            except DriveFault:
                pytest.fail("a strict drive must not make back-to-back set-points fail")
        r = drives.report()
        assert wait_until(lambda: sum(s.stats["setpoints"] for s in sims.drives) == r["edges"], 1.0)
        assert r["edges"] >= 10                      # about half get through; fewer on a loaded machine
        assert r["edges"] + r["missed"] >= 2 * 20
        assert all(s.stats["ignored_edges"] == 0 for s in sims.drives)
        assert r["missed_per_drive"] == {1: drives.drives[0].missed_total, 2: drives.drives[1].missed_total}


def test_persistent_missed_setpoints_trip_the_supervisor():
    with rig(behaviour=ELMO_LIKE) as (cfg, sims, drives):
        drives.home()
        safe = SafeDrives(drives, SafetyConfig(monitor_period=0.0), close_inner=False)
        safe.send_setpoints(np.array([10, 10]))
        sim = sims[cfg.node_ids[1]]
        sim._new_setpoint = lambda cw: None       # the drive keeps sending status but takes no set-point
        with pytest.raises(SafetyTrip, match="not taken"):
            for k in range(100):
                safe.send_setpoints(np.array([20 + k, 20 + k]))
                time.sleep(0.02)
        assert drives.drives[1].missed_total >= 3
        assert drives.report()["missed"] >= 3
        assert safe.tripped
        safe.close()


# ---------------------------------------------------------------- item 2: a failed enable ends disabled

def test_failed_enable_leaves_every_drive_disabled():
    with rig() as (cfg, sims, drives):
        drives.disable()
        sims[cfg.node_ids[1]].inject_fault(0x5441, persistent=True)    # STO on the y drive
        with pytest.raises(DriveFault):
            drives.enable()
        # the x drive had reached operation enabled before the y drive failed: it must be off again
        assert sims[cfg.node_ids[0]].state == State.SWITCH_ON_DISABLED
        assert sims[cfg.node_ids[1]].state == State.FAULT
        with pytest.raises(DriveFault):
            drives.send_setpoints(np.array([0, 0]))


# ---------------------------------------------------------------- item 3: NMT pre-operational, reaction settings

def test_startup_writes_the_drives_reaction_settings_and_enables_emcy():
    cfg_over = dict(comm_error_behaviour=2, abort_connection_option=3, quick_stop_option=1, shutdown_option=0,
                    disable_operation_option=0, halt_option=2, fault_reaction_option=1)
    with rig(start_driver=False, **cfg_over) as (cfg, sims, _):
        for s in sims.drives:
            s._params_od[(o.EMCY_COB_ID, 0)] |= o.PDO_COB_INVALID       # factory setting: EMCY off
        with CanopenDrives(cfg) as drives:
            for s in sims.drives:
                p = s._params_od
                assert p[(o.ERROR_BEHAVIOUR, 1)] == 2 and p[(o.ABORT_CONNECTION_OPTION, 0)] == 3
                assert (p[(o.QUICK_STOP_OPTION, 0)], p[(o.SHUTDOWN_OPTION, 0)], p[(o.DISABLE_OPERATION_OPTION, 0)],
                        p[(o.HALT_OPTION, 0)], p[(o.FAULT_REACTION_OPTION, 0)]) == (1, 0, 0, 2, 1)
                assert p[(o.CONSUMER_HEARTBEAT, 1)] == (cfg.master_node_id << 16) | round(cfg.drive_consumer_timeout * 1e3)
                assert not p[(o.EMCY_COB_ID, 0)] & o.PDO_COB_INVALID
            drives.home()
            sims[cfg.node_ids[0]].inject_fault(0x2310)
            assert wait_until(lambda: drives.fault() is not None and "0x2310" in drives.fault(), 1.0)


def test_reenable_recovers_a_drive_that_went_pre_operational_on_a_lost_host_heartbeat():
    with rig(master_heartbeat_period=0.02, drive_consumer_timeout=0.1) as (cfg, sims, drives):
        drives.home()
        drives._master_hb.stop()                 # the host stalls without disabling the drives
        # defaults: 0x1029:1 = 0 (pre-operational) and 0x6007 = 1 (fault)
        assert wait_until(lambda: all(s.nmt_state == "PRE-OPERATIONAL" and s.state == State.FAULT
                                      for s in sims.drives), 2.0)
        assert wait_until(lambda: drives.fault() is not None and "left NMT operational" in drives.fault(), 1.0)
        assert "0x8130" in drives.fault()
        drives._master_hb = drives.network.send_periodic(0x700 + cfg.master_node_id, [0x05], 0.02)
        drives.enable()                          # NMT start + fault reset + enable, no restart needed
        assert [s.nmt_state for s in sims.drives] == ["OPERATIONAL"] * 2
        assert drives.fault() is None
        drives.send_setpoints(np.array([500, -500]))
        assert wait_until(lambda: np.all(np.abs(drives.positions() - [500, -500]) <= 25), 2.0)


# ---------------------------------------------------------------- item 4: disable confirmed or reported

def test_disable_is_repeated_until_the_drives_confirm_it_after_a_link_loss():
    # the host-heartbeat watch is off (allowed by the docs): the drives keep their state on link loss
    with rig(drive_consumer_timeout=0.0, master_heartbeat_period=0.0, heartbeat_timeout=0.1) as (cfg, sims, drives):
        drives.home()
        safe = SafeDrives(drives, SafetyConfig(monitor_period=0.01), close_inner=False)
        for s in sims.drives:
            s.set_silent(True)                   # cable pulled
        assert wait_until(lambda: safe.tripped, 2.0)
        assert all(s.state == State.OPERATION_ENABLED for s in sims.drives)   # nothing got through
        assert wait_until(lambda: "disable not confirmed" in (drives.fault() or ""), 2.0)
        for s in sims.drives:
            s.set_silent(False)                  # cable back: the retried disable gets through
        assert wait_until(lambda: all(s.state == State.SWITCH_ON_DISABLED for s in sims.drives), 3.0)
        assert wait_until(lambda: "disable not confirmed" not in (drives.fault() or ""), 1.0)
        assert drives.stats["disable_retries"] > 0
        safe.close()


def test_sdo_only_disable_is_retried_until_a_hung_sdo_server_answers():
    with rig(use_pdo=False) as (cfg, sims, drives):
        drives.home()
        for s in sims.drives:
            s.set_sdo_mute(True)
        drives.disable()
        assert "disable not confirmed" in drives.fault()
        assert all(s.state == State.OPERATION_ENABLED for s in sims.drives)
        for s in sims.drives:
            s.set_sdo_mute(False)
        assert wait_until(lambda: all(s.state == State.SWITCH_ON_DISABLED for s in sims.drives), 3.0)
        assert wait_until(lambda: "disable not confirmed" not in (drives.fault() or ""), 1.0)


def test_disable_by_rpdo_when_sdo_does_not_answer():
    with rig(behaviour=ELMO_LIKE) as (cfg, sims, drives):
        drives.home()
        for s in sims.drives:
            s.set_sdo_mute(True)
        drives.disable()
        assert all(s.state == State.SWITCH_ON_DISABLED for s in sims.drives)
        assert "disable not confirmed" not in (drives.fault() or "")


def test_drive_leaving_operation_enabled_is_noticed_while_setpoints_are_held():
    with rig() as (cfg, sims, drives):
        drives.home()
        safe = SafeDrives(drives, SafetyConfig(monitor_period=0.01), close_inner=False)
        sim = sims[cfg.node_ids[0]]
        with sim._lock:
            sim._apply_controlword(o.CW_SHUTDOWN)      # the drive drops out without a fault
            sim._after_change()
        assert wait_until(lambda: safe.tripped, 1.0)  # no set-point was sent meanwhile
        assert "left operation enabled" in safe.fault()
        safe.close()


# ---------------------------------------------------------------- item 5: timing parameters checked together

def test_timing_parameters_are_checked_against_each_other():
    with pytest.raises(ConfigError, match="tpdo_period = 0.05 s must be shorter than .*setpoint_ack_timeout"):
        replace(CanopenRigConfig(), tpdo_period=0.05).check()
    with pytest.raises(ConfigError, match="status_timeout"):
        replace(CanopenRigConfig(), tpdo_period=0.008, status_timeout=0.01).check()
    CanopenRigConfig().check_timing(50.0)
    with pytest.raises(ConfigError, match="setpoint_ack_timeout = 0.015 s must be at most half the loop period"):
        replace(CanopenRigConfig(), setpoint_ack_timeout=0.015).check_timing(50.0)
    with pytest.raises(ConfigError, match="sdo_timeout"):
        replace(CanopenRigConfig(), use_pdo=False).check_timing(50.0)


def test_report_gives_the_cost_of_each_setpoint_call():
    with rig(behaviour=ELMO_LIKE) as (cfg, sims, drives):
        drives.home()
        for k in range(10):
            drives.send_setpoints(np.array([k, k]))
        r = drives.report()
        assert r["setpoints"] == 10
        assert 0 < r["setpoint_call_ms"]["p50"] <= r["setpoint_call_ms"]["max"]


# ---------------------------------------------------------------- item 6: only status produced after the command

def test_homing_is_not_completed_by_a_stale_homing_attained():
    with rig(behaviour=ELMO_LIKE, homing_method=21, tpdo_period=0.008, initial_angles=(0.02, 0.02)) \
            as (cfg, sims, drives):
        drives.home()
        assert np.all(np.abs(sims.angles()) < 1e-3)
        # whether a stale status is the latest one at the check depends on the PDO timer's phase: repeat
        for _ in range(3):
            drives.send_setpoints(np.array([4000, 4000]))       # 0.064 rad away from home
            assert wait_until(lambda: np.all(np.abs(drives.positions() - 4000) <= 25), 2.0)
            # homing mode still shows "homing attained" from the last homing until the new one starts
            drives.home()
            assert drives.homed
            assert np.all(np.abs(sims.angles()) < 1e-3), "home() returned before the homing motion ended"
            assert np.all(np.abs(drives.positions()) <= 25)


# ---------------------------------------------------------------- item 7: clamp before the integer cast

@pytest.mark.parametrize("huge", [2.0 ** 63, 1e300])
def test_huge_finite_setpoints_go_to_the_right_limit(huge):
    with rig(min_angle=-0.1, max_angle=0.1) as (cfg, sims, drives):
        drives.home()
        drives.send_setpoints(np.array([huge, -huge]))
        assert sims[cfg.node_ids[0]]._target_active == cfg.max_ticks
        assert sims[cfg.node_ids[1]]._target_active == cfg.min_ticks


# ---------------------------------------------------------------- item 8: a late drive is not waited for

def test_a_silent_drive_does_not_block_the_setpoint_call():
    # a long SDO timeout: any SDO fallback inside send_setpoints would show as a call of >= 0.5 s
    with rig(sdo_timeout=0.5, heartbeat_timeout=5.0, status_timeout=0.15) as (cfg, sims, drives):
        drives.home()
        sims[cfg.node_ids[1]].set_silent(True)
        worst = 0.0
        for k in range(3):
            t0 = time.monotonic()
            drives.send_setpoints(np.array([100 * k, 100 * k]))
            worst = max(worst, time.monotonic() - t0)
        assert worst < 0.25
        assert drives.drives[1].missed_total == 3
        time.sleep(cfg.status_timeout)
        with pytest.raises(DriveFault, match="not taken|no status PDO"):
            drives.send_setpoints(np.array([300, 300]))


def test_slow_sdo_drive_still_starts_and_moves():
    with rig(behaviour=SimDriveBehaviour(sdo_delay=0.01)) as (cfg, sims, drives):
        drives.home()
        drives.send_setpoints(np.array([300, -300]))
        assert wait_until(lambda: np.all(np.abs(drives.positions() - [300, -300]) <= 25), 2.0)


# ---------------------------------------------------------------- item 9: smaller ones

def test_sdo_timeout_in_sdo_only_mode_shows_in_fault():
    with rig(use_pdo=False) as (cfg, sims, drives):
        drives.home()
        sims[cfg.node_ids[0]].set_sdo_mute(True)
        # no command needed: the monitor polls the statusword in SDO-only mode
        assert wait_until(lambda: "no SDO answer" in (drives.fault() or ""), 2.0)


def test_abort_0x06090031_has_its_text():
    assert sdo_abort_text(0x06090031) == "value of parameter written too high"


def test_link_loss_is_found_by_the_missing_status_pdos_before_the_heartbeat_timeout():
    with rig(status_timeout=0.05, heartbeat_timeout=2.0) as (cfg, sims, drives):
        drives.home()
        sims[cfg.node_ids[0]].set_silent(True)
        assert wait_until(lambda: drives.fault() is not None, 1.5)
        assert "no status PDO" in drives.fault() and "heartbeat" not in drives.fault()


# ---------------------------------------------------------------- item 10: the drive's EDS

def test_driver_runs_on_the_drives_eds(tmp_path):
    eds = tmp_path / "drive.eds"
    canopen.export_od(o.build_object_dictionary(1), str(eds), doc_type="eds")
    with rig(eds_file=str(eds)) as (cfg, sims, drives):
        assert isinstance(drives.drives[0].node.object_dictionary, canopen.ObjectDictionary)
        assert drives.drives[0].node.object_dictionary[o.TARGET_POSITION].data_type == canopen.objectdictionary.INTEGER32
        drives.home()
        drives.send_setpoints(np.array([200, 200]))
        assert wait_until(lambda: np.all(np.abs(drives.positions() - 200) <= 25), 2.0)
    with pytest.raises(ConfigError, match="eds_file"):
        replace(CanopenRigConfig(), eds_file=str(tmp_path / "missing.eds")).check()


def test_cyclic_synchronous_position_with_sync():
    with rig(operation_mode="cyclic_sync_position", sync_period=0.005, homing_method=21,
             initial_angles=(0.01, -0.01)) as (cfg, sims, drives):
        sim = sims[cfg.node_ids[0]]
        assert sim._mode == o.MODE_CYCLIC_SYNC_POSITION
        assert sim._tpdos[0].trans_type == 1 and sim._rpdos[0].trans_type == 1
        assert sim._params_od[(o.INTERPOLATION_PERIOD, 1)] == 5
        drives.home()                                  # homing mode, then back to cyclic synchronous
        assert sim._mode == o.MODE_CYCLIC_SYNC_POSITION and np.all(np.abs(sims.angles()) < 1e-3)
        n_sync = sim.stats["sync"]
        for k in range(1, 26):                         # a 50 Hz ramp of targets, as the loop sends them
            drives.send_setpoints(np.array([40 * k, -40 * k]))
            time.sleep(0.02)
        assert sim.stats["sync"] - n_sync >= 25        # the SYNC producer runs (5 ms)
        assert wait_until(lambda: np.all(np.abs(drives.positions() - [1000, -1000]) <= 25), 2.0)
        r = drives.report()
        assert r["edges"] == 50 and r["acked_in_call"] >= 40     # the drives showed "following"
        assert sim.stats["setpoints"] >= 20                       # targets were taken at the SYNCs
    with pytest.raises(ConfigError, match="use_pdo"):
        replace(CanopenRigConfig(), operation_mode="cyclic_sync_position", use_pdo=False).check()
    with pytest.raises(ConfigError, match="sync_period"):
        replace(CanopenRigConfig(), operation_mode="cyclic_sync_position", sync_period=0.03).check_timing(50.0)


def test_positions_of_a_lost_drive_raise_at_once_instead_of_waiting_for_sdo():
    with rig(status_timeout=0.05, sdo_timeout=1.0, heartbeat_timeout=5.0) as (cfg, sims, drives):
        drives.home()
        sims[cfg.node_ids[1]].set_silent(True)
        assert wait_until(lambda: drives.fault() is not None, 1.5)
        time.sleep(drives.drives[1].pdo_stale_after)
        t0 = time.monotonic()
        with pytest.raises(DriveFault, match="no status PDO"):
            drives.positions()
        assert time.monotonic() - t0 < 0.5          # an SDO read would wait the full 1 s timeout

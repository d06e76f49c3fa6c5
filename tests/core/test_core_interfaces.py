"""The drum controller's contract is four roles (setpoints, commands, monitor, calibration) and their union: each
role is a runtime-checkable Protocol a part can be typed against alone, and the Modbus client meets every one."""

from __future__ import annotations

from rigctl.core.drum import DrumState, DrumStatus, Fault
from rigctl.core.interfaces import DrumCalibration, DrumCommands, DrumController, DrumMonitor, DrumSetpoints
from rigctl.devices.drum import DrumClient


class _Clock:
    def now(self) -> float:
        return 0.0

    def sleep(self, s: float) -> None:
        pass


class StatusOnly:
    """A monitor and nothing else (e.g. what a status display needs)."""

    clock = _Clock()

    def read_status(self):
        return DrumStatus(0.0, 0.0, 0.0, 0.0, 0, 0.0, DrumState.IDLE, Fault(0), (1, 0), 0, 0, 0.0)

    def settings(self):
        return {}

    def wait_state(self, states, timeout_s):
        return self.read_status()

    def wait_released(self, timeout_s, home_mm=0.05):
        return self.read_status()

    def wait_force_settled(self, timeout_s):
        return self.read_status()

    def wait_speed_steady(self, timeout_s, tol_mm_s=0.5, n_polls=3):
        return self.read_status()


def test_a_role_is_met_alone_and_the_union_needs_every_role():
    m = StatusOnly()
    assert isinstance(m, DrumMonitor)
    assert not isinstance(m, DrumController) and not isinstance(m, DrumCommands)
    assert not isinstance(m, DrumSetpoints) and not isinstance(m, DrumCalibration)


def test_the_modbus_client_meets_every_role():
    client = DrumClient("/dev/null-not-opened")  # not opened: only its methods are looked at
    for role in (DrumSetpoints, DrumCommands, DrumMonitor, DrumCalibration, DrumController):
        assert isinstance(client, role), role.__name__


def test_every_protocol_method_is_documented():
    import inspect

    from rigctl.core import drum, interfaces

    protocols = [c for m in (interfaces, drum) for _, c in inspect.getmembers(m, inspect.isclass)
                 if c.__module__ == m.__name__ and getattr(c, "_is_protocol", False)]
    assert len(protocols) >= 9
    undocumented = [f"{c.__name__}.{name}" for c in protocols for name, f in vars(c).items()
                    if callable(f) or isinstance(f, property)
                    if not name.startswith("__") or name in ("__enter__", "__exit__")
                    if not (f.__doc__ or "").strip()]
    assert not undocumented, undocumented

"""The interface the link hands the flight controller's state to, message by message, on the link thread
(:class:`mavvo.service.timing.FlightControllerState` implements it; a replay's driver feeds the same one)."""

from __future__ import annotations

from typing import Protocol

__all__ = ["LinkListener"]


class LinkListener(Protocol):
    """Receives the flight controller's state from the link thread (see :mod:`mavvo.service.timing`)."""

    def on_attitude(
        self,
        t_fc_ms: int,
        roll_rad: float,
        pitch_rad: float,
        yaw_rad: float,
        t_arrival_host_s: float | None = None,
        body_rates_rad_s: tuple[float, float, float] | None = None,
    ) -> None: ...
    def on_local_position(
        self,
        t_fc_ms: int,
        p_ned_m: tuple[float, float, float],
        v_ned_m_s: tuple[float, float, float],
        t_arrival_host_s: float | None = None,
    ) -> None: ...
    def on_range(self, t_fc_ms: int, range_m: float | None, t_arrival_host_s: float | None = None) -> None: ...
    def on_height(self, t_fc_ms: int, height_m: float, t_arrival_host_s: float | None = None) -> None: ...
    def on_timesync(self, t_sent_host_s: float, t_fc_s: float, t_arrival_host_s: float | None = None) -> None: ...
    def on_reboot(self) -> None: ...
    def on_armed(self, armed: bool, t_arrival_host_s: float | None = None) -> None: ...
    def on_ekf_status(
        self, attitude_good: bool, compass_ratio: float, t_arrival_host_s: float | None = None
    ) -> None: ...
    def wants_timesync(self) -> bool: ...

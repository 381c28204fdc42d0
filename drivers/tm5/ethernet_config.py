"""Settings of the TM5-700 over its Ethernet Slave and Listen node (`devices.arm.settings`, protocol tm-ethernet)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from drivers.configio import join, load_dataclass, require
from drivers.tm5.config import check_stale_periods


@dataclass(frozen=True)
class TMEthernetConfig:
    """Where the controller is and how the host closes the position loop over velocity streaming."""

    host: str
    slave_port: int = 5891  # Ethernet Slave: the data table broadcast ($TMSVR)
    listen_port: int = 5890  # Listen node: scripts ($TMSCT) and status ($TMSTA)
    connect_timeout_s: float = 5.0  # per socket connect, and for the first data table to arrive
    link_lost_after_s: float = 1.0  # no table for this long: the link is lost (TM's own drivers use 1 s)
    # While armed, no new table for this long stops the arm (StaleDataError): moving on frozen state for
    # TM's 1 s would be 64 periods blind.  A few broadcast periods, so one late or merged packet passes.
    stale_after_s: float = 0.06
    reply_timeout_s: float = 1.0  # arm(): wait this long for the Listen node's answers
    # Position loop on the host: joint speed = feed-forward + position_gain * (target - measured) [1/s].
    # The feed-forward alone makes the controller's integrated target the streamed one; the gain only
    # corrects the drift of speeds applied for a jittered period.  A stiffer loop integrates the tracking
    # error in contact, where the impedance law expects a position servo: at 4-20 1/s the wipe's force
    # overshot (101-110 N) and never settled at 15.6 ms; at 1 1/s it settles as over Modbus.
    position_gain: float = 1.0

    def validate(self, where: str = "tm_ethernet") -> None:
        """ConfigError naming the first bad field."""
        require(bool(self.host.strip()), join(where, "host"), "must be the controller's address, got ''")
        for name in ("slave_port", "listen_port"):
            value = getattr(self, name)
            require(1 <= value <= 65535, join(where, name), f"must lie in 1-65535, got {value}")
        require(self.slave_port != self.listen_port, join(where, "listen_port"),
                f"must differ from slave_port ({self.slave_port})")
        require(0 < self.connect_timeout_s <= 60, join(where, "connect_timeout_s"),
                f"must lie in (0, 60] s, got {self.connect_timeout_s}")
        require(0.05 <= self.link_lost_after_s <= 10, join(where, "link_lost_after_s"),
                f"must lie in [0.05, 10] s (the table arrives every ~16 ms), got {self.link_lost_after_s}")
        require(0.001 <= self.stale_after_s <= 1.0, join(where, "stale_after_s"),
                f"must lie in [0.001, 1] s (the arm moves on frozen data this long), got {self.stale_after_s}")
        require(self.stale_after_s <= self.link_lost_after_s, join(where, "stale_after_s"),
                f"must be <= link_lost_after_s ({self.link_lost_after_s:g} s), got {self.stale_after_s}")
        require(0 < self.reply_timeout_s <= 30, join(where, "reply_timeout_s"),
                f"must lie in (0, 30] s, got {self.reply_timeout_s}")
        require(0 <= self.position_gain <= 20, join(where, "position_gain"),
                f"must lie in [0, 20] 1/s, got {self.position_gain}")

    def check_period(self, dt: float, where: str = "tm_ethernet") -> None:
        """Stale data is a few control periods at least: a shorter limit trips on the broadcast's jitter."""
        check_stale_periods(self.stale_after_s, dt, where)

    @classmethod
    def from_dict(cls, data: Any, where: str) -> TMEthernetConfig:
        """Typed, bounded loading: one-line ConfigError naming `<where>.<field>` on any bad value."""
        return load_dataclass(cls, data, where)

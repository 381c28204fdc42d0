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
    # The controller's own Modbus table (joint angles, error, E-stop, running) read as a cross-check of the
    # Ethernet Slave's by doctor, status and the first arm() on new links; None: the cell has no Modbus server
    # to read (route B needs none: enabling it is a separate TMflow switch, so the check is asked for, not
    # assumed).  TM's is 502.
    modbus_port: int | None = None
    connect_timeout_s: float = 5.0  # per socket connect, and for the first data table to arrive
    link_lost_after_s: float = 1.0  # no table for this long: the link is lost (TM's own drivers use 1 s)
    # While armed, no new table for this long stops the arm (StaleDataError): moving on frozen state for
    # TM's 1 s would be 64 periods blind.  A few broadcast periods, so one late or merged packet passes.
    stale_after_s: float = 0.06
    # Waits on the Listen node outside the control loop: the first arm on a connection, doctor's probes, the
    # stop's confirmation when closing.
    reply_timeout_s: float = 1.0
    # The streamed scripts' replies come back on later polls.  More than this many unanswered, or the oldest
    # unanswered for longer than max_reply_age_s, and the node queues what it cannot run at once: the arm
    # stops (ListenBacklogError, a lost link).  About three periods' worth at the 15.6 ms broadcast period.
    max_unanswered_scripts: int = 3
    max_reply_age_s: float = 0.05
    # Position loop on the host: joint speed = feed-forward + position_gain * (target - joints ahead) [1/s].
    # The feed-forward alone makes the controller's integrated target the streamed one; the gain corrects
    # what timing does to it (a speed applied for a late or missed period, one clipped at a limit).
    position_gain: float = 0.3
    # Periods from a speed's send until the broadcast shows its effect: the loop's "joints ahead" add the
    # speeds sent over these periods.  2 with no queueing (the table is one period old and the servo
    # interpolates over one), plus the periods of doctor's command round trip beyond its first.  Counted
    # short, the gain pushes again for motion already on its way and a contact force rings.
    command_latency_periods: int = 2

    def validate(self, where: str = "tm_ethernet") -> None:
        """ConfigError naming the first bad field."""
        require(bool(self.host.strip()), join(where, "host"), "must be the controller's address, got ''")
        for name in ("slave_port", "listen_port"):
            value = getattr(self, name)
            require(1 <= value <= 65535, join(where, name), f"must lie in 1-65535, got {value}")
        require(self.slave_port != self.listen_port, join(where, "listen_port"),
                f"must differ from slave_port ({self.slave_port})")
        if self.modbus_port is not None:
            require(1 <= self.modbus_port <= 65535, join(where, "modbus_port"),
                    f"must lie in 1-65535 (TM's Modbus server: 502), or be null for no cross-check, got "
                    f"{self.modbus_port}")
            require(self.modbus_port not in (self.slave_port, self.listen_port), join(where, "modbus_port"),
                    f"must differ from slave_port ({self.slave_port}) and listen_port ({self.listen_port})")
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
        require(1 <= self.max_unanswered_scripts <= 64, join(where, "max_unanswered_scripts"),
                f"must lie in 1..64 scripts (a few control periods' worth), got {self.max_unanswered_scripts}")
        require(0.005 <= self.max_reply_age_s <= self.link_lost_after_s, join(where, "max_reply_age_s"),
                f"must lie in [0.005 s, link_lost_after_s ({self.link_lost_after_s:g} s)], got {self.max_reply_age_s}")
        require(0 <= self.position_gain <= 20, join(where, "position_gain"),
                f"must lie in [0, 20] 1/s, got {self.position_gain}")
        require(0 <= self.command_latency_periods <= 10, join(where, "command_latency_periods"),
                f"must lie in 0..10 periods (doctor's command round trip), got {self.command_latency_periods}")

    def check_period(self, dt: float, where: str = "tm_ethernet") -> None:
        """Stale data is a few control periods at least: a shorter limit trips on the broadcast's jitter.  So is
        a reply's allowed age: a reply normally comes back within the period its script went out in."""
        check_stale_periods(self.stale_after_s, dt, where)
        require(self.max_reply_age_s >= 2 * dt - 1e-12, join(where, "max_reply_age_s"),
                f"must be >= 2 control periods ({2 * dt:g} s at {dt:g} s), got {self.max_reply_age_s!r}")

    @classmethod
    def from_dict(cls, data: Any, where: str) -> TMEthernetConfig:
        """Typed, bounded loading: one-line ConfigError naming `<where>.<field>` on any bad value."""
        return load_dataclass(cls, data, where)

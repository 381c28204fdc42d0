"""`--view`: the Rerun live view of a run, a bench trial or a replay (spawned viewer, or served for a browser)."""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from cell.model.robot import RobotModel

log = logging.getLogger("tmcell")


def add_view_options(sp: Any, what: str) -> None:
    """--view and --serve on a command's parser."""
    sp.add_argument("--view", action="store_true", help=f"{what}: stream it to the Rerun viewer (spawned)")
    sp.add_argument("--serve", action="store_true",
                    help="with --view: serve the view for a browser instead (headless machines; Ctrl+C ends it)")
    sp.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                    help="with --view: the address the viewer listens on (default 127.0.0.1: this machine only; "
                         "0.0.0.0 lets other machines open it)")


def has_display() -> bool:
    """Whether a spawned viewer has a screen to open on (X11 and Wayland need their variable set)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _headless(serve: bool) -> bool:
    """True (said in one line) when --view would spawn a viewer on a machine without a display: a viewer
    that cannot open leaves the stream waiting for it after the run."""
    if serve or has_display():
        return False
    log.warning("--view: no display (DISPLAY/WAYLAND_DISPLAY unset), no viewer spawned; add --serve to view "
                "it in a browser")
    return True


def live_view(robot: RobotModel, name: str, serve: bool, virtual_in_loop: bool, bind: str = "127.0.0.1") -> Any:
    """A RunView streaming to a spawned viewer or to a served web viewer (listening on `bind`); None on a
    headless machine without --serve."""
    from cell.view.rerun_view import BackgroundView, RunView, open_viewer

    if _headless(serve):
        return None

    return BackgroundView(RunView(open_viewer(name, serve, bind), robot, virtual_in_loop))


def finish_view(view: Any, serve: bool) -> None:
    """Flush the stream; a served view lives in this process, so it stays up until Ctrl+C."""
    if view is None:
        return
    close = getattr(view, "close", None)
    if callable(close):
        close()
    view.rec.flush()
    if serve:
        from cell.view.rerun_view import stop_servers

        log.info("the view stays served until Ctrl+C")
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            stop_servers()


def view_replay(run_dir: Path, robot: RobotModel, estimates: np.ndarray, label: str, serve: bool,
                virtual_in_loop: bool, bind: str = "127.0.0.1") -> None:
    """The recorded run in the viewer with the replayed virtual wrench beside it (`wrench/replay/*`)."""
    if _headless(serve):
        return
    import rerun as rr

    from cell.data.recorder import read_log
    from cell.view.rerun_view import AXES, TIMELINE, RunView, log_table, open_viewer

    table = read_log(run_dir)
    view = RunView(open_viewer(f"replay-{Path(run_dir).name}", serve, bind), robot, virtual_in_loop)
    log_table(view, table)
    t = np.asarray(table.column("t").to_numpy(zero_copy_only=False), float)
    for k, axis in enumerate(AXES):
        view.rec.send_columns(f"wrench/replay/{axis}", indexes=[rr.TimeColumn(TIMELINE, duration=t)],
                              columns=rr.Scalars.columns(scalars=estimates[:, k]))
    view.event(f"replayed with {label}")
    finish_view(view, serve)

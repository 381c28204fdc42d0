"""The Rerun view of a run: the arm, the TCP path, virtual and measured wrenches, setpoint, task state, safety events.

Two ways in: `write_rrd` turns a run's Parquet step log into `recording.rrd` beside it (every recorded
run), and `LiveView` streams the same entities row by row to a spawned viewer or a browser (`--view`).
Entity layout (what the test reads back): `arm/links` (line strip through the joint origins and the TCP),
`arm/geometry/boxes|cylinders` (the URDF's collision shapes where the joints put them),
`arm/tcp_path` (the TCP's path so far), `wrench/<virtual|sensor>/arrow` (force at the TCP, world axes,
`ARROW_M_PER_N` metres per newton), `wrench/<virtual|sensor>/<fx..mz>`, `wrench/setpoint/fz` and
`wrench/limit/<axis>/<which>` (time series), `joints/torque/<j>` (measured joint torques),
`collision/ratio` (the collision residual over its threshold), `contact/depth_mm` (series), `task/state`,
`contact/state` and `events` (text logs).  The timeline is `time`, the run's own clock.  Every stream and
`.rrd` carries the blueprint (`blueprint()`): one chart per wrench axis with both sensors, the setpoint and
the limits; the joint torques, the collision ratio and the depth; the states and events; the arm once.
"""

from __future__ import annotations

import logging
import queue
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import pinocchio as pin
import pyarrow as pa
import rerun as rr

from cell.model.robot import RobotModel
from drivers.errors import ConfigError

log = logging.getLogger(__name__)

AXES = ("fx", "fy", "fz", "mx", "my", "mz")
ARROW_M_PER_N = 0.002  # 100 N draws a 0.2 m arrow: visible beside a 0.7 m arm
FRAME_EVERY = 4  # 3-D frames every 4th control period (32 ms at 125 Hz): the viewer need not draw faster
APP_ID = "tmcell"
TIMELINE = "time"
WEB_PORT = 9090  # the served web viewer (its gRPC data stream is on GRPC_PORT)
GRPC_PORT = 9876
LOCAL = "127.0.0.1"
SERVER_START_S = 20.0  # how long the served viewer may take to listen
# The served viewers this process started (ended by `stop_servers`).
_SERVERS: list[subprocess.Popen[bytes]] = []


def _viewer_binary() -> str | None:
    # The viewer ships in the rerun-sdk wheel, beside this interpreter: found even with the venv inactive.
    beside = Path(sys.executable).with_name("rerun")
    return str(beside) if beside.exists() else None


def _host(addr: str) -> str:
    # An IPv6 address goes in brackets in a URL.
    return f"[{addr}]" if ":" in addr else addr


def serve_viewer(bind: str = LOCAL, web_port: int = WEB_PORT, grpc_port: int = GRPC_PORT,
                 web: bool = True) -> tuple[str, str]:
    """Start Rerun's viewer listening on `bind` only: with `web`, the web viewer and its gRPC proxy (ended by
    `stop_servers`), else the native viewer window (left open for the user); (the gRPC URL for the SDK, the
    page's URL for a browser).  The SDK's own serve_grpc / serve_web_viewer / spawn listen on every interface
    with no way to narrow it: the viewer binary's `--bind` does, so it runs as a child process."""
    near = LOCAL if bind in ("0.0.0.0", "::", "") else bind  # a wildcard is reached through the loopback
    grpc = f"rerun+http://{_host(near)}:{grpc_port}/proxy"
    page = f"http://{_host(near)}:{web_port}/?url={quote(grpc, safe='')}"
    if not web and _listening(near, grpc_port):
        return grpc, page  # a viewer window is already open there: log into it
    exe = _viewer_binary() or "rerun"
    cmd = [exe, "--bind", bind, "--port", str(grpc_port)]
    if web:
        cmd += ["--serve-web", "--web-viewer-port", str(web_port)]
    err_file = tempfile.TemporaryFile()  # noqa: SIM115 (a file, not a pipe: a long-lived viewer never blocks on it)
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err_file,
                                start_new_session=not web)
    except OSError as exc:
        raise ConfigError(f"--view: cannot start the Rerun viewer ({exc})") from None
    if web:
        _SERVERS.append(proc)
    deadline = time.monotonic() + SERVER_START_S
    while True:
        if proc.poll() is not None:
            err_file.seek(0)
            err = err_file.read().decode(errors="replace").strip().splitlines()
            raise ConfigError(f"--view on {bind}: the Rerun viewer stopped ({err[-1] if err else proc.returncode})"
                              "; is the port in use, the address not this machine's"
                              + (", or no display (add --serve)?" if not web else "?"))
        if _listening(near, grpc_port):
            break
        if time.monotonic() > deadline:
            stop_servers()
            raise ConfigError(f"--view on {bind}: the Rerun viewer did not listen on port {grpc_port} "
                              f"within {SERVER_START_S:.0f} s")
        time.sleep(0.2)
    return grpc, page


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def stop_servers() -> None:
    """End the served viewers this process started."""
    while _SERVERS:
        proc = _SERVERS.pop()
        proc.terminate()
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()


def open_viewer(name: str, serve: bool, bind: str = LOCAL) -> rr.RecordingStream:
    """A recording stream to a spawned viewer, or (headless) served for a browser on `bind`; the URL is logged."""
    rec = rr.RecordingStream(APP_ID, recording_id=name)
    grpc, page = serve_viewer(bind, web=serve)
    rec.connect_grpc(grpc)
    rec.send_blueprint(blueprint())
    if serve:
        log.info("Rerun view served on %s: open %s in a browser", bind, page)
    return rec


class ArmFrames:
    """The arm's drawable geometry at a posture (Pinocchio on the cell's URDF): joint origins, TCP, and the
    URDF's collision shapes (boxes and cylinders) where the posture puts them."""

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        try:
            self.geom = pin.buildGeomFromUrdf(robot.model, str(robot.urdf), pin.GeometryType.COLLISION)
            self.geom_data = self.geom.createData()
        except (RuntimeError, ValueError) as exc:  # a URDF without shapes still draws as a line
            log.debug("no URDF geometry for the view: %s", exc)
            self.geom = None

    def at(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m, d = self.robot.model, self.robot.data
        pin.forwardKinematics(m, d, np.asarray(q, float))
        tcp = pin.updateFramePlacement(m, d, self.robot.tcp_id)
        joints = np.array([d.oMi[i].translation for i in range(1, m.njoints)])
        points = np.vstack([np.zeros(3), joints, tcp.translation])
        return points, tcp.translation.copy(), tcp.rotation.copy()

    def shapes(self) -> dict[str, Any]:
        """The collision shapes at the posture of the last `at` call, as Rerun archetypes by entity name."""
        if self.geom is None:
            return {}
        pin.updateGeometryPlacements(self.robot.model, self.robot.data, self.geom, self.geom_data)
        boxes: dict[str, list[Any]] = {"centers": [], "half_sizes": [], "quaternions": []}
        cyl: dict[str, list[Any]] = {"centers": [], "radii": [], "lengths": [], "quaternions": []}
        for obj, placement in zip(self.geom.geometryObjects, self.geom_data.oMg, strict=True):
            g = obj.geometry
            quat = rr.Quaternion(xyzw=pin.Quaternion(placement.rotation).coeffs())
            if hasattr(g, "halfSide"):
                boxes["centers"].append(placement.translation.copy())
                boxes["half_sizes"].append(np.asarray(g.halfSide, float))
                boxes["quaternions"].append(quat)
            elif hasattr(g, "halfLength") and hasattr(g, "radius"):
                cyl["centers"].append(placement.translation.copy())
                cyl["radii"].append(float(g.radius))
                cyl["lengths"].append(2.0 * float(g.halfLength))
                cyl["quaternions"].append(quat)
        out: dict[str, Any] = {}
        if boxes["centers"]:
            out["arm/geometry/boxes"] = rr.Boxes3D(centers=boxes["centers"], half_sizes=boxes["half_sizes"],
                                                   quaternions=boxes["quaternions"], fill_mode="solid")
        if cyl["centers"]:
            out["arm/geometry/cylinders"] = rr.Cylinders3D(lengths=cyl["lengths"], radii=cyl["radii"],
                                                           centers=cyl["centers"], quaternions=cyl["quaternions"],
                                                           fill_mode="solid")
        return out


def _wrench(row: Mapping[str, Any], prefix: str) -> np.ndarray | None:
    keys = [prefix + a for a in AXES]
    if any(k not in row or row[k] is None for k in keys):
        return None
    return np.array([float(row[k]) for k in keys])


def blueprint(n_joints: int = 6) -> Any:
    """The layout every view and `.rrd` opens with: the arm on the left; on the right one chart per wrench
    axis (virtual and F/T, setpoint, limits), the joint torques, the collision ratio with the contact depth,
    and the task's states and events."""
    import rerun.blueprint as rrb

    def axis(a: str) -> Any:
        return rrb.TimeSeriesView(origin="/", name=a.capitalize(), contents=[
            f"wrench/virtual/{a}", f"wrench/sensor/{a}", f"wrench/replay/{a}", f"wrench/setpoint/{a}",
            f"wrench/limit/{a}/**"])

    charts = rrb.Grid(*[axis(a) for a in AXES], grid_columns=3)
    below = rrb.Horizontal(
        rrb.TimeSeriesView(origin="joints/torque", name="joint torques (N·m)"),
        rrb.TimeSeriesView(origin="/", name="collision ratio, depth (mm)",
                           contents=["collision/ratio", "contact/depth_mm"]),
        rrb.TextLogView(origin="/", name="states and events", contents=["task/state", "contact/state", "events"]),
    )
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="/", name="arm", contents=["arm/**", "wrench/*/arrow"]),
        rrb.Vertical(charts, below, row_shares=[2, 1]), column_shares=[1, 2]), collapse_panels=True)


class RunView:
    """Logs rows of the step log (dicts as the control loop records them) into a recording stream."""

    def __init__(self, rec: rr.RecordingStream, robot: RobotModel, virtual_in_loop: bool) -> None:
        self.rec = rec
        self.contact = ""
        self.frames = ArmFrames(robot)
        self.n = robot.n
        # The loop's own wrench columns are the virtual sensor's when it regulates, else the F/T sensor's.
        self.sources = {"virtual": "", "sensor": "sensor_"} if virtual_in_loop else {"sensor": ""}
        self.path: list[np.ndarray] = []
        self.state = ""
        self.rows = 0
        rec.log("arm", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def row(self, row: Mapping[str, Any], series: bool = True) -> None:
        """One control period: the series every time (unless sent as columns), the 3-D scene every FRAME_EVERY."""
        rec = self.rec
        rec.set_time(TIMELINE, duration=float(row["t"]))
        state = str(row.get("state", ""))
        if state != self.state:
            rec.log("task/state", rr.TextLog(state, level=rr.TextLogLevel.INFO))
            self.state = state
        contact = row.get("contact_state", row.get("contact"))
        if isinstance(contact, str) and contact != self.contact:
            rec.log("contact/state", rr.TextLog(contact, level=rr.TextLogLevel.INFO))
            self.contact = contact
        reaction = row.get("reaction")
        if isinstance(reaction, str) and reaction:
            rec.log("events", rr.TextLog(f"collision reaction: {reaction}", level=rr.TextLogLevel.WARN))
        if series:
            for name, prefix in self.sources.items():
                w = _wrench(row, prefix)
                if w is not None:
                    for axis, v in zip(AXES, w, strict=True):
                        rec.log(f"wrench/{name}/{axis}", rr.Scalars(v))
            if row.get("fz_setpoint") is not None:
                rec.log("wrench/setpoint/fz", rr.Scalars(float(row["fz_setpoint"])))
            for entity, col in self.series().items():
                if row.get(col) is not None:
                    rec.log(entity, rr.Scalars(float(row[col]) * (1e3 if col == "depth" else 1.0)))
        if self.rows % FRAME_EVERY == 0:
            self._scene(row)
        self.rows += 1

    def series(self) -> dict[str, str]:
        """The other time series by entity: step-log column (joint torques, collision ratio, depth)."""
        out = {f"joints/torque/{j + 1}": f"tau{j + 1}" for j in range(self.n)}
        out.update({"collision/ratio": "coll_ratio", "contact/depth_mm": "depth"})
        return out

    def limits(self, limits: Mapping[str, Sequence[tuple[str, float]]], t0: float, t1: float) -> None:
        """Each wrench limit as a flat line over [t0, t1] (`wrench/limit/<axis>/<name>`), at +- its value."""
        times = [rr.TimeColumn(TIMELINE, duration=[t0, t1])]
        for axis, entries in limits.items():
            for name, value in entries:
                for sign, tag in ((1.0, ""), (-1.0, "_neg")):
                    self.rec.send_columns(f"wrench/limit/{axis}/{name.replace(' ', '_')}{tag}", indexes=times,
                                          columns=rr.Scalars.columns(scalars=[sign * value] * 2))

    def _scene(self, row: Mapping[str, Any]) -> None:
        q = np.array([float(row[f"q{i + 1}"]) for i in range(self.n)])
        points, tcp, rot = self.frames.at(q)
        self.path.append(tcp)
        self.rec.log("arm/links", rr.LineStrips3D([points], radii=0.01))
        for entity, shape in self.frames.shapes().items():
            self.rec.log(entity, shape)
        self.rec.log("arm/tcp_path", rr.LineStrips3D([np.asarray(self.path)], radii=0.002))
        for name, prefix in self.sources.items():
            w = _wrench(row, prefix)
            if w is not None and np.all(np.isfinite(w[:3])):
                self.rec.log(f"wrench/{name}/arrow",
                             rr.Arrows3D(origins=[tcp], vectors=[rot @ w[:3] * ARROW_M_PER_N]))

    def event(self, text: str, warn: bool = False) -> None:
        self.rec.log("events", rr.TextLog(text, level=rr.TextLogLevel.WARN if warn else rr.TextLogLevel.INFO))


def log_table(view: RunView, table: pa.Table, summary: Mapping[str, Any] | None = None,
              limits: Mapping[str, Sequence[tuple[str, float]]] | None = None) -> None:
    """A whole step log into `view`: the series as columns (one call per series), the limits as lines, the
    scene and the states row by row, the run's outcome as the last event."""
    rec = view.rec
    t = np.asarray(table.column("t").to_numpy(zero_copy_only=False), float)
    times = [rr.TimeColumn(TIMELINE, duration=t)]
    names = set(table.column_names)
    series = {f"wrench/{name}/{axis}": prefix + axis for name, prefix in view.sources.items() for axis in AXES}
    series["wrench/setpoint/fz"] = "fz_setpoint"
    series.update(view.series())
    for entity, col in series.items():
        if col in names:
            values = np.asarray(table.column(col).to_numpy(zero_copy_only=False), float)
            if col == "depth":
                values = values * 1e3
            rec.send_columns(entity, indexes=times, columns=rr.Scalars.columns(scalars=values))
    if limits and len(t):
        view.limits(limits, float(t[0]), float(t[-1]))
    for row in table.to_pylist():
        view.row(row, series=False)
    if summary:
        outcome = str(summary.get("outcome", ""))
        reason = str(summary.get("reason") or "")
        view.event(f"outcome: {outcome}" + (f" ({reason})" if reason else ""), warn=outcome != "done")


def write_rrd(run_dir: Path, table: pa.Table, robot: RobotModel, summary: Mapping[str, Any],
              limits: Mapping[str, Sequence[tuple[str, float]]] | None = None) -> Path:
    """The run's step log as `recording.rrd` in `run_dir` with its blueprint (open with `rerun recording.rrd`)."""
    path = Path(run_dir) / "recording.rrd"
    rec = rr.RecordingStream(APP_ID, recording_id=Path(run_dir).name)
    rec.save(path, default_blueprint=blueprint(robot.n))
    log_table(RunView(rec, robot, summary.get("force_source") == "virtual"), table, summary, limits)
    rec.flush()
    rec.disconnect()
    return path


class BackgroundView:
    """A RunView fed from the control loop through a bounded queue and logged on its own thread: the
    loop only enqueues a row (microseconds); when the viewer falls behind, rows are dropped, never waited for."""

    def __init__(self, view: RunView, max_rows: int = 2000) -> None:
        self.view = view
        self.rec = view.rec
        self.dropped = 0
        self._q: queue.Queue[tuple[str, Any] | None] = queue.Queue(max_rows)
        self._full = queue.Full
        self._thread = threading.Thread(target=self._drain, name="rerun-view", daemon=True)
        self._thread.start()

    def row(self, row: Mapping[str, Any]) -> None:
        self._put(("row", dict(row)))

    def event(self, text: str, warn: bool = False) -> None:
        self._put(("event", (text, warn)))

    def _put(self, item: tuple[str, Any]) -> None:
        try:
            self._q.put_nowait(item)
        except self._full:
            self.dropped += 1

    def _drain(self) -> None:
        while (item := self._q.get()) is not None:
            kind, payload = item
            try:
                if kind == "row":
                    self.view.row(payload)
                else:
                    self.view.event(*payload)
            except Exception as exc:  # the viewer's trouble ends the view, not the run
                log.warning("live view stopped: %s", exc)
                return

    def close(self) -> None:
        """Log what is queued, then stop the thread."""
        self._q.put(None)
        self._thread.join(timeout=30.0)
        if self.dropped:
            log.warning("live view: %d rows dropped (the viewer fell behind the loop)", self.dropped)

"""ROS 1 bags, ROS 2 bags (SQLite or MCAP) and bare ``.mcap`` files as sequences, through ``rosbags``
(pure Python, no ROS install; the optional extra ``[ros]``).

:class:`BagWriter` writes a drive as ROS users expect it; :class:`BagSequence` reads such a bag, or any
bag with ``sensor_msgs/PointCloud2`` scans, as the localizer and the map builder read a KITTI folder.

Layout written (REP 105 frames; every stamp is the sweep's end, as the KITTI folder's ``times.txt``):

=================  ==========================  ===============================================================
topic              type                        content
=================  ==========================  ===============================================================
``/points``        sensor_msgs/PointCloud2     frame ``lidar``; x y z intensity (f32), time (f32, s, <= 0 from
                                               the stamp), ring, column (u16), label (u8: 1 = moving actor)
``/tf_static``     tf2_msgs/TFMessage          ``base_link`` -> ``lidar`` (the mount), ``map`` -> ``odom``
``/tf``            tf2_msgs/TFMessage          ``odom`` -> ``base_link`` (odometry), ``map`` ->
                                               ``base_link_truth`` (the true pose, in its own frame)
``/odom``          nav_msgs/Odometry           ``odom`` -> ``base_link``: wheel + gyro odometry
``/ground_truth``  nav_msgs/Odometry           ``map`` -> ``base_link_truth``
``/imu``           sensor_msgs/Imu             frame ``base_link``: roll and pitch (orientation; its yaw: the
                                               odometry's), gravity as linear acceleration
``/actors``        visualization_msgs/         frame ``map``: one box per moving actor
                   MarkerArray
``/simbed/meta``   std_msgs/String             the drive's ``meta.yaml`` (sensor, scene, seed, ...), written
                                               last, with ``complete`` and ``frames``
=================  ==========================  ===============================================================

A bag is complete only when closed: an MCAP or ROS 1 bag of a recording killed outright (SIGKILL, power
loss) has no index and cannot be read; stopped by Ctrl-C or SIGTERM it is closed, readable, and its meta
says ``complete: false``. Record to a KITTI folder when a kill must leave a readable prefix.
"""

from __future__ import annotations

import bisect
import contextlib
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from rangemcl.datasets import pointcloud2 as pc2
from rangemcl.datasets.recording import Recording
from rangemcl.errors import InputError
from rangemcl.se2 import interpolate_poses, invert_rigid, matrix_from_quat, quat_from_matrix

FORMATS = ("mcap", "rosbag2", "rosbag1")
INSTALL = "pip install 'simbed-rangemcl[ros]'"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
TF = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
META_TOPIC = "/simbed/meta"
TRUTH_TOPIC = "/ground_truth"


def require_rosbags(what: str):
    try:
        import rosbags  # noqa: F401
    except ImportError:
        raise InputError(f"{what} needs rosbags: {INSTALL}") from None


def is_bag(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a bag: a ``.bag``, ``.mcap`` or ``.db3`` file, or a ROS 2 bag folder."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix in (".bag", ".mcap", ".db3")


def stamp_ns(t: float) -> int:
    """Nanoseconds of a time in seconds, through its 9-decimal text (as ``times.txt`` writes it), so that
    ``stamp_ns(t) / 1e9`` reads back as the folder's time does."""
    text = f"{t:.9f}"
    whole, frac = text.split(".")
    sign = -1 if whole.startswith("-") else 1
    return sign * (abs(int(whole)) * 1_000_000_000 + int(frac))


# --- writing ---------------------------------------------------------------------------------------------


def _time(ts, ns: int):
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class BagWriter:
    """Write a drive frame by frame as a bag; :meth:`add_frame` takes what
    :meth:`rangemcl.datasets.kitti.SequenceWriter.add_frame` takes (plus the actors' boxes).

    ``fmt``: ``mcap`` (a ROS 2 bag folder holding one ``.mcap`` file, which Foxglove opens alone),
    ``rosbag2`` (a ROS 2 bag folder, SQLite) or ``rosbag1`` (a ``.bag`` file). ``T_base_sensor`` is the
    LiDAR's mount on the car (poses given are the LiDAR's, as in the folder)."""

    def __init__(
        self,
        out: str | os.PathLike,
        fmt: str,
        *,
        meta: dict[str, Any] | None = None,
        T_base_sensor: np.ndarray | None = None,
        overwrite: bool = False,
    ) -> None:
        if fmt not in FORMATS:
            raise InputError(f"format {fmt!r}: expected one of {', '.join(FORMATS)} (or kitti)")
        require_rosbags(f"--format {fmt}")
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.out = Path(out)
        self.fmt = fmt
        self.meta = dict(meta or {})
        self.meta.pop("complete", None)
        self.T_base_sensor = np.eye(4) if T_base_sensor is None else np.asarray(T_base_sensor, np.float64)
        self._T_sensor_base = invert_rigid(self.T_base_sensor)
        self.ros1 = fmt == "rosbag1"
        if self.ros1 and self.out.suffix != ".bag":
            raise InputError(f"{self.out}: a ROS 1 bag is a file ending in .bag")
        if not self.ros1 and self.out.suffix in (".bag", ".mcap", ".db3"):
            raise InputError(
                f"{self.out}: a ROS 2 bag ({fmt}) is a folder; give a name without {self.out.suffix}"
            )
        self._prepare(overwrite)
        ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:  # the ROS 1 store lacks TFMessage: same layout as ROS 2's
            ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
        self.ts = ts
        self._frames = 0
        self._last_time: float | None = None
        self._last_ns = 0
        self._prev_odom: tuple[float, np.ndarray] | None = None
        self._closed = False
        self._open_writer()

    def _prepare(self, overwrite: bool) -> None:
        out = self.out
        if out.exists() or out.is_symlink():
            if not overwrite:
                raise InputError(f"{out}: exists (give --overwrite to replace the bag)")
            if not is_bag(out):
                raise InputError(f"{out}: exists and is not a bag; refusing to overwrite")
            try:
                shutil.rmtree(out) if out.is_dir() and not out.is_symlink() else out.unlink()
            except OSError as err:
                raise InputError(f"{out}: cannot remove the old bag ({err.strerror})") from None
        parent = out.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputError(f"{out}: cannot create the folder it goes in ({err.strerror})") from None

    def _open_writer(self) -> None:
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self._w = Writer(self.out)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if self.fmt == "mcap" else StoragePlugin.SQLITE3
            self._w = Writer(self.out, version=9, storage_plugin=plugin)
        self._w.open()
        latched = self._latched_kwargs()
        add = self._w.add_connection
        self._con = {
            "/points": add("/points", POINTCLOUD2, typestore=self.ts),
            "/tf_static": add("/tf_static", TF, typestore=self.ts, **latched),
            "/tf": add("/tf", TF, typestore=self.ts),
            "/odom": add("/odom", ODOMETRY, typestore=self.ts),
            TRUTH_TOPIC: add(TRUTH_TOPIC, ODOMETRY, typestore=self.ts),
            "/imu": add("/imu", IMU, typestore=self.ts),
            "/actors": add("/actors", "visualization_msgs/msg/MarkerArray", typestore=self.ts),
            META_TOPIC: add(META_TOPIC, STRING, typestore=self.ts, **latched),
        }

    def _latched_kwargs(self) -> dict:
        if self.ros1:
            return {"latching": 1}
        from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

        z = QosTime(sec=0, nsec=0)
        qos = Qos(
            QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
            z, z, QosLiveliness.AUTOMATIC, z, False,
        )  # fmt: skip
        return {"offered_qos_profiles": [qos]}

    # -- messages

    def _header(self, ns: int, frame_id: str):
        t = self.ts.types
        kw = {"seq": self._frames} if self.ros1 else {}
        return t["std_msgs/msg/Header"](stamp=_time(self.ts, ns), frame_id=frame_id, **kw)

    def _write(self, topic: str, ns: int, msg) -> None:
        raw = (
            self.ts.serialize_ros1(msg, msg.__msgtype__)
            if self.ros1
            else self.ts.serialize_cdr(msg, msg.__msgtype__)
        )
        self._w.write(self._con[topic], ns, raw)

    def _pose_msg(self, T: np.ndarray):
        t = self.ts.types
        q = quat_from_matrix(T[:3, :3])
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            orientation=t["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
            ),
        )

    def _transform(self, ns: int, parent: str, child: str, T: np.ndarray):
        t = self.ts.types
        q = quat_from_matrix(T[:3, :3])
        tf = t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=t["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
            ),
        )
        return t["geometry_msgs/msg/TransformStamped"](
            header=self._header(ns, parent), child_frame_id=child, transform=tf
        )

    def _odometry(self, ns: int, parent: str, child: str, T: np.ndarray, v: np.ndarray, w: np.ndarray):
        t = self.ts.types
        cov = np.zeros(36)
        vec = t["geometry_msgs/msg/Vector3"]
        twist = t["geometry_msgs/msg/Twist"](
            linear=vec(x=v[0], y=v[1], z=v[2]), angular=vec(x=w[0], y=w[1], z=w[2])
        )
        return t[ODOMETRY](
            header=self._header(ns, parent),
            child_frame_id=child,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose_msg(T), covariance=cov),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov.copy()),
        )

    def add_frame(
        self,
        points: Any,
        *,
        pose: Any,
        time_s: float,
        intensity: Any = None,
        odometry: Any = None,
        imu_roll_pitch: Any = None,
        point_meta: dict[str, Any] | None = None,
        actors: list[dict] | None = None,
    ) -> int:
        """Write one frame (``pose``: the LiDAR's true pose, or None when there is none). ``actors``: dicts
        with ``name``, ``kind``, ``xyz``, ``quat_wxyz``, ``half`` (box half-sizes, m) and ``rgba``."""
        if self._closed:
            raise RuntimeError(f"{self.out}: BagWriter is closed")
        t = float(time_s)
        where = f"{self.out}: frame {self._frames}"
        if not math.isfinite(t) or t <= 0:
            raise InputError(f"{where}: time {t} must be finite and > 0 (ROS stamps start after 0)")
        if self._last_time is not None and t <= self._last_time:
            raise InputError(f"{where}: time {t:.9g} is not after the previous frame's {self._last_time:.9g}")
        ns = stamp_ns(t)
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        extra: dict[str, np.ndarray] = {
            "intensity": np.zeros(len(pts), np.float32)
            if intensity is None
            else np.asarray(intensity, np.float32).reshape(-1)
        }
        for key, value in (point_meta or {}).items():
            name = "time" if key == "time_s" else key
            a = np.asarray(value)
            extra[name] = a.astype(np.float32) if name == "time" else a
        fields, data, step = pc2.encode(pts, extra)
        types = self.ts.types
        pf = types["sensor_msgs/msg/PointField"]
        msg = types[POINTCLOUD2](
            header=self._header(ns, "lidar"),
            height=1,
            width=len(pts),
            fields=[pf(name=f.name, offset=f.offset, datatype=f.datatype, count=1) for f in fields],
            is_bigendian=False,
            point_step=step,
            row_step=step * len(pts),
            data=np.frombuffer(data, np.uint8),
            is_dense=True,
        )
        self._write("/points", ns, msg)
        T_world_base = None if pose is None else np.asarray(pose, np.float64) @ self._T_sensor_base
        T_odom_base = None if odometry is None else np.asarray(odometry, np.float64) @ self._T_sensor_base
        transforms = []
        if self._frames == 0:
            static = [self._transform(ns, "base_link", "lidar", self.T_base_sensor)]
            if T_odom_base is not None and T_world_base is not None:
                static.append(self._transform(ns, "map", "odom", T_world_base @ invert_rigid(T_odom_base)))
            self._write("/tf_static", ns, types[TF](transforms=static))
        zero = np.zeros(3)
        if T_odom_base is not None:
            v = w = zero
            if self._prev_odom is not None:
                t0, T0 = self._prev_odom
                d = invert_rigid(T0) @ T_odom_base
                dt = t - t0
                v = d[:3, 3] / dt
                w = np.array([0.0, 0.0, math.atan2(d[1, 0], d[0, 0]) / dt])
            self._prev_odom = (t, T_odom_base)
            self._write("/odom", ns, self._odometry(ns, "odom", "base_link", T_odom_base, v, w))
            transforms.append(self._transform(ns, "odom", "base_link", T_odom_base))
        if T_world_base is not None:
            truth = self._odometry(ns, "map", "base_link_truth", T_world_base, zero, zero)
            self._write(TRUTH_TOPIC, ns, truth)
            transforms.append(self._transform(ns, "map", "base_link_truth", T_world_base))
        if transforms:
            self._write("/tf", ns, types[TF](transforms=transforms))
        if imu_roll_pitch is not None:
            self._write("/imu", ns, self._imu(ns, imu_roll_pitch, T_odom_base))
        if actors is not None:
            self._write("/actors", ns, self._markers(ns, actors))
        self._frames += 1
        self._last_time = t
        self._last_ns = ns
        return self._frames - 1

    def _imu(self, ns: int, roll_pitch, T_odom_base):
        roll, pitch = (float(v) for v in np.asarray(roll_pitch, np.float64).reshape(2))
        yaw = 0.0 if T_odom_base is None else math.atan2(T_odom_base[1, 0], T_odom_base[0, 0])
        R = _rz(yaw) @ _ry(pitch) @ _rx(roll)
        q = quat_from_matrix(R)
        t = self.ts.types
        g = R.T @ np.array([0.0, 0.0, 9.81])  # what an accelerometer at rest reads, in the body frame
        vec = t["geometry_msgs/msg/Vector3"]
        big = 1e3  # the yaw is the odometry's: not a measurement
        return t[IMU](
            header=self._header(ns, "base_link"),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            orientation_covariance=np.array([1e-6, 0, 0, 0, 1e-6, 0, 0, 0, big]),
            angular_velocity=vec(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=np.array([-1.0, 0, 0, 0, 0, 0, 0, 0, 0]),
            linear_acceleration=vec(x=g[0], y=g[1], z=g[2]),
            linear_acceleration_covariance=np.zeros(9),
        )

    def _markers(self, ns: int, actors: list[dict]):
        t = self.ts.types
        marker = t["visualization_msgs/msg/Marker"]
        extra = {}
        if not self.ros1:
            extra = {
                "texture_resource": "",
                "texture": t["sensor_msgs/msg/CompressedImage"](
                    header=self._header(ns, ""), format="", data=np.zeros(0, np.uint8)
                ),
                "uv_coordinates": [],
                "mesh_file": t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
            }
        duration = t["builtin_interfaces/msg/Duration"]
        out = []
        for k, a in enumerate(actors):
            w, x, y, z = (float(v) for v in a["quat_wxyz"])
            T = np.eye(4)
            T[:3, :3] = matrix_from_quat(np.array([x, y, z, w]))
            T[:3, 3] = a["xyz"]
            r, g, b, alpha = (float(v) for v in a.get("rgba", (0.8, 0.2, 0.2, 1.0)))
            half = [float(v) for v in a["half"]]
            out.append(
                marker(
                    header=self._header(ns, "map"),
                    ns=str(a.get("kind", "actor")),
                    id=k,
                    type=1,  # CUBE
                    action=0,
                    pose=self._pose_msg(T),
                    scale=t["geometry_msgs/msg/Vector3"](x=2 * half[0], y=2 * half[1], z=2 * half[2]),
                    color=t["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=alpha),
                    lifetime=duration(sec=0, nanosec=200_000_000),
                    frame_locked=False,
                    points=[],
                    colors=[],
                    text=str(a.get("name", "")),
                    mesh_resource="",
                    mesh_use_embedded_materials=False,
                    **extra,
                )
            )
        return t["visualization_msgs/msg/MarkerArray"](markers=out)

    # -- meta and closing

    def update_meta(self, **items: Any) -> None:
        items.pop("complete", None)
        self.meta.update(items)

    def __len__(self) -> int:
        return self._frames

    def close(self, *, complete: bool = True) -> None:
        """Write the meta message (with ``complete`` and ``frames``) and the bag's index."""
        if self._closed:
            return
        self._closed = True
        try:
            text = yaml.safe_dump(
                {**self.meta, "frames": self._frames, "complete": bool(complete)}, sort_keys=False
            )
            ns = max(self._last_ns, 1)
            self._write(META_TOPIC, ns, self.ts.types[STRING](data=text))
        finally:
            self._w.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close(complete=exc_type is None)
        return False


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# --- reading ---------------------------------------------------------------------------------------------


@dataclass
class BagOptions:
    """How to read a bag: topics (``None``: the only one of its type, or the usual name), the sensor's
    mounting when the bag's TF lacks it, ground truth from a poses file, the per-point time field."""

    lidar_topic: str | None = None
    imu_topic: str | None = None
    odom_topic: str | None = None
    truth_topic: str | None = None
    sensor_to_base: tuple[float, ...] | None = None  # x y z (m) roll pitch yaw (deg)
    base_frame: str | None = None
    poses_file: str | None = None  # the LiDAR's poses: TUM (time x y z qx qy qz qw) or KITTI (one a scan)
    point_time_field: str | None = None
    point_time_unit: str | None = None
    scan_stamp: str | None = None  # "start" | "end": what a scan's stamp marks; None: detected


def _T(translation, quat_xyzw) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.asarray(quat_xyzw, np.float64))
    T[:3, 3] = translation
    return T


def _tf_of(tf) -> tuple[str, str, np.ndarray]:
    tr, q = tf.transform.translation, tf.transform.rotation
    return (
        tf.header.frame_id.lstrip("/"),
        tf.child_frame_id.lstrip("/"),
        _T((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w)),
    )


def _pose_of(p) -> np.ndarray:
    return _T(
        (p.position.x, p.position.y, p.position.z),
        (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w),
    )


def _stamp_s(header) -> float:
    return (header.stamp.sec * 1_000_000_000 + header.stamp.nanosec) / 1e9  # correctly rounded


def sensor_to_base_transform(values) -> np.ndarray:
    """``x y z roll pitch yaw`` (m, degrees) as ``T_base_sensor``."""
    v = [float(x) for x in values]
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise InputError(
            f"--sensor-to-base {values}: expected 6 finite numbers x,y,z,roll,pitch,yaw (m, deg)"
        )
    from rangemcl.se2 import transform_from_xyz_rpy

    return transform_from_xyz_rpy(v[:3], v[3:])


@dataclass
class BagSequence(Recording):
    """A bag read as a sequence: the same attributes and methods as :class:`rangemcl.datasets.kitti.Sequence`.

    Scans are decoded when asked for (the last one is kept); poses, odometry, times and IMU roll/pitch are
    read at opening, from the small topics."""

    root: Path
    topic: str
    calib_source: str = field(default="identity (bag scans are in the sensor frame)", kw_only=True)
    stamp_to_end_s: float = 0.0
    odometry_source: str = "none"
    _log_ns: list[int] = field(default_factory=list, repr=False)
    _options: BagOptions = field(default_factory=BagOptions, repr=False)
    _time_field: str | None = None
    _cache: tuple[int, pc2.Cloud, np.ndarray | None] | None = field(default=None, repr=False)
    _reader: Any = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self._log_ns)

    @property
    def scan_paths(self) -> list[str]:
        """One name per scan (bag, topic, stamp): what a resume fingerprint lists."""
        return [f"{self.root}:{self.topic}@{ns}" for ns in self._log_ns]

    def _index(self, i: int) -> int:
        n = len(self)
        k = int(i) + (n if int(i) < 0 else 0)
        if not 0 <= k < n:
            raise InputError(f"{self.root}: frame {i} out of range (the bag has {n} scans on {self.topic})")
        return k

    def _decode(self, i: int) -> tuple[pc2.Cloud, np.ndarray | None]:
        k = self._index(i)
        if self._cache is not None and self._cache[0] == k:
            return self._cache[1], self._cache[2]
        r = self._reader
        cons = [c for c in r.connections if c.topic == self.topic]
        ns = self._log_ns[k]
        # the k-th message of the topic: several may share a log time
        rank = k - bisect.bisect_left(self._log_ns, ns)  # log times are in order
        for j, (con, _, raw) in enumerate(r.messages(connections=cons, start=ns, stop=ns + 1)):
            if j == rank:
                msg = r.deserialize(raw, con.msgtype)
                break
        else:  # pragma: no cover - the index pass saw it
            raise InputError(f"{self.root}: scan {k} of {self.topic} cannot be found again")
        where = f"{self.root}: {self.topic} scan {k}"
        cloud = pc2.decode(
            msg.fields, msg.data, width=msg.width, height=msg.height, point_step=msg.point_step,
            row_step=msg.row_step, is_bigendian=bool(msg.is_bigendian), where=where,
        )  # fmt: skip
        rel = None
        name = pc2.find_time_field(cloud.fields, self._time_field)
        if name is not None:
            rel = pc2.point_times(
                cloud.fields.pop(name), _stamp_s(msg.header), unit=self._options.point_time_unit, where=where
            )
        self._cache = (k, cloud, rel)
        return cloud, rel

    def scan(self, i: int) -> np.ndarray:
        return self._decode(i)[0].points

    def scan_with_intensity(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        cloud = self._decode(i)[0]
        return cloud.points, cloud.intensity

    def point_meta(self, i: int) -> dict[str, np.ndarray]:
        """The scan's other fields, with its per-point times as ``time_s`` (float32 seconds from the frame's
        time, <= 0 when the stamp is the sweep's end)."""
        cloud, rel = self._decode(i)
        out = {k: v for k, v in cloud.fields.items() if v.ndim == 1}
        if rel is not None and len(rel) and np.ptp(rel) > 0:
            out["time_s"] = (rel - self.stamp_to_end_s).astype(np.float32)
        return out

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def __enter__(self) -> BagSequence:
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    def __del__(self) -> None:  # pragma: no cover - best effort
        with contextlib.suppress(Exception):
            self.close()


def _kind(msgtype: str) -> str:
    """``pkg/msg/Name`` and ``pkg/Name`` (ROS 1 style, some MCAP writers) alike."""
    return msgtype.replace("/msg/", "/")


def _topics_line(reader) -> str:
    return ", ".join(
        f"{name} ({t.msgtype.split('/')[-1]}, {t.msgcount})" for name, t in sorted(reader.topics.items())
    )


def _pick_topic(
    reader, given: str | None, msgtypes: tuple[str, ...], usual: tuple[str, ...], what: str, path
) -> str | None:
    topics = reader.topics
    if given is not None:
        if given not in topics:
            raise InputError(f"{path}: no topic {given} ({what}); the bag has: {_topics_line(reader)}")
        if _kind(topics[given].msgtype) not in {_kind(m) for m in msgtypes}:
            raise InputError(
                f"{path}: topic {given} holds {topics[given].msgtype}, not {' or '.join(msgtypes)} ({what})"
            )
        return given
    found = [
        n for n, t in topics.items() if _kind(t.msgtype) in {_kind(m) for m in msgtypes} and t.msgcount > 0
    ]
    for name in usual:
        if name in found:
            return name
    return found[0] if len(found) == 1 else None


def _stamped_poses(reader, topic: str) -> tuple[np.ndarray, np.ndarray, str, str]:
    """Stamps and poses of an Odometry topic: ``(S,)`` seconds, ``(S, 4, 4)``, its frame and child frame."""
    cons = [c for c in reader.connections if c.topic == topic]
    stamps, poses, frame, child = [], [], "", ""
    for con, _, raw in reader.messages(connections=cons):
        m = reader.deserialize(raw, con.msgtype)
        stamps.append(_stamp_s(m.header))
        poses.append(_pose_of(m.pose.pose))
        frame, child = m.header.frame_id.lstrip("/"), m.child_frame_id.lstrip("/")
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps)[order], np.asarray(poses).reshape(-1, 4, 4)[order], frame, child


def _at(stamps: np.ndarray, poses: np.ndarray, times: np.ndarray, what: str, path) -> np.ndarray:
    """Poses at ``times``: the sample itself where a stamp matches to the nanosecond, else interpolated;
    times outside the samples (by more than 1 ms) are an error."""
    if len(stamps) == 0:
        raise InputError(f"{path}: {what} has no messages")
    outside = (times < stamps[0] - 1e-3) | (times > stamps[-1] + 1e-3)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        raise InputError(
            f"{path}: scan {k} at {times[k]:.6f} s is outside {what}'s span "
            f"({stamps[0]:.6f}-{stamps[-1]:.6f} s): are both on the same clock?"
        )
    out = interpolate_poses(stamps, poses, times)
    k = np.clip(np.searchsorted(stamps, times), 0, len(stamps) - 1)
    exact = np.abs(stamps[k] - times) < 5e-10
    out[exact] = poses[k[exact]]
    return out


def _static_tree(reader) -> dict[tuple[str, str], np.ndarray]:
    """Transforms ``(parent, child) -> T_parent_child`` from ``/tf_static`` (and ``/tf`` edges that never
    change over the bag: a sensor mount published on /tf)."""
    edges: dict[tuple[str, str], np.ndarray] = {}
    moving: set[tuple[str, str]] = set()
    for topic in ("/tf_static", "/tf"):
        if topic not in reader.topics:
            continue
        cons = [c for c in reader.connections if c.topic == topic]
        for con, _, raw in reader.messages(connections=cons):
            for tf in reader.deserialize(raw, con.msgtype).transforms:
                parent, child, T = _tf_of(tf)
                key = (parent, child)
                if topic == "/tf" and key in edges and not np.allclose(edges[key], T, atol=1e-9):
                    moving.add(key)
                edges.setdefault(key, T)
    return {k: v for k, v in edges.items() if k not in moving}


def _chain(edges: dict[tuple[str, str], np.ndarray], base: str, sensor: str) -> np.ndarray | None:
    """``T_base_sensor`` through the static tree (either direction along each edge), or None."""
    graph: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (p, c), T in edges.items():
        graph.setdefault(p, []).append((c, T))
        graph.setdefault(c, []).append((p, invert_rigid(T)))
    seen, todo = {base}, [(base, np.eye(4))]
    while todo:
        frame, T = todo.pop()
        if frame == sensor:
            return T
        for nxt, step in graph.get(frame, []):
            if nxt not in seen:
                seen.add(nxt)
                todo.append((nxt, T @ step))
    return None


def open_bag(
    path: str | os.PathLike, options: BagOptions | None = None, *, require_poses: bool = False
) -> BagSequence:
    """Open a bag as a sequence (checks the topics, reads the small topics, indexes the scans)."""
    opt = options or BagOptions()
    require_rosbags(f"reading {path}")
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error

    root = Path(path)
    if not root.exists():
        raise InputError(f"{root}: no such bag")
    try:
        reader = AnyReader([root])
        reader.open()
    except (AnyReaderError, Reader1Error, Reader2Error, OSError, ValueError, KeyError) as err:
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InputError(f"{root}: cannot read the bag ({text})") from None
    try:
        return _open(reader, root, opt, require_poses)
    except BaseException:
        reader.close()
        raise


def _open(reader, root: Path, opt: BagOptions, require_poses: bool) -> BagSequence:
    topic = _pick_topic(reader, opt.lidar_topic, (POINTCLOUD2,), ("/points",), "LiDAR scans", root)
    if topic is None:
        clouds = [n for n, t in reader.topics.items() if _kind(t.msgtype) == _kind(POINTCLOUD2)]
        if clouds:
            raise InputError(
                f"{root}: several PointCloud2 topics ({', '.join(sorted(clouds))}): give --lidar-topic"
            )
        raise InputError(
            f"{root}: no sensor_msgs/PointCloud2 topic; the bag has: {_topics_line(reader) or 'nothing'}"
        )
    seq = BagSequence(root=root, topic=topic, _options=opt, _reader=reader)
    seq._time_field = opt.point_time_field
    # meta: a simbed recording's own
    if META_TOPIC in reader.topics:
        cons = [c for c in reader.connections if c.topic == META_TOPIC]
        for con, _, raw in reader.messages(connections=cons):
            try:
                data = yaml.safe_load(reader.deserialize(raw, con.msgtype).data)
            except yaml.YAMLError:
                data = None
            if isinstance(data, dict):
                seq.meta = data
    # the scans' index: log times and header stamps
    cons = [c for c in reader.connections if c.topic == topic]
    stamps, frame_id = [], None
    try:
        for con, log_ns, raw in reader.messages(connections=cons):
            m = reader.deserialize(raw, con.msgtype)
            seq._log_ns.append(int(log_ns))
            stamps.append(_stamp_s(m.header))
            frame_id = frame_id or m.header.frame_id.lstrip("/")
    except Exception as err:  # rosbags raises many kinds on damaged data
        raise InputError(
            f"{root}: cannot read {topic} ({str(err).splitlines()[0] if str(err) else type(err).__name__})"
        ) from None
    if not seq._log_ns:
        raise InputError(f"{root}: {topic} has no messages")
    times = np.asarray(stamps, np.float64)
    bad = np.flatnonzero(np.diff(times) < 0)
    if len(bad):
        raise InputError(f"{root}: {topic} scan {bad[0] + 1} is stamped before the scan before it")
    seq.times = times
    _stamp_convention(seq, opt)
    seq.times = seq.times + seq.stamp_to_end_s
    # the mount
    edges = _static_tree(reader)
    odom_topic = _pick_topic(reader, opt.odom_topic, (ODOMETRY,), ("/odom", "/odometry"), "odometry", root)
    if opt.odom_topic is None and odom_topic in (TRUTH_TOPIC, opt.truth_topic):
        odom_topic = None
    odom = _stamped_poses(reader, odom_topic) if odom_topic else None
    base = opt.base_frame or (odom[3] if odom else None) or "base_link"
    if opt.sensor_to_base is not None:
        T_base_sensor = sensor_to_base_transform(opt.sensor_to_base)
        mount_source = "--sensor-to-base"
    else:
        T_base_sensor = _chain(edges, base, frame_id or "") if frame_id else None
        mount_source = f"TF {base} -> {frame_id}"
        if T_base_sensor is None:
            if frame_id and frame_id == base:
                T_base_sensor, mount_source = np.eye(4), "the scans are in the base frame"
            else:
                frames = sorted({f for edge in edges for f in edge})
                raise InputError(
                    f"{root}: no static transform from {base} to the scans' frame {frame_id!r} "
                    f"(TF frames: {', '.join(frames) or 'none'}); give --sensor-to-base x,y,z,roll,pitch,yaw"
                )
    from rangemcl.se2 import xyz_rpy_from_transform

    xyz, rpy = xyz_rpy_from_transform(T_base_sensor)
    seq.meta["sensor_to_base"] = {"xyz_m": xyz, "rpy_deg": rpy, "source": mount_source}
    if odom is not None:
        seq.odometry = _at(odom[0], odom[1], seq.times, f"odometry {odom_topic}", root) @ T_base_sensor
        seq.odometry_source = f"{odom_topic} (the bag's odometry)"
    # ground truth
    if opt.poses_file is not None:
        seq.poses = poses_at_scans(Path(opt.poses_file), seq.times)
    else:
        present = TRUTH_TOPIC in reader.topics and reader.topics[TRUTH_TOPIC].msgcount > 0
        truth_topic = opt.truth_topic or (TRUTH_TOPIC if present else None)
        if truth_topic is not None:
            _pick_topic(reader, truth_topic, (ODOMETRY,), (), "ground truth", root)
            st, P, _, _ = _stamped_poses(reader, truth_topic)
            seq.poses = _at(st, P, seq.times, f"ground truth {truth_topic}", root) @ T_base_sensor
    if require_poses and seq.poses is None:
        raise InputError(f"{root}: no ground-truth poses (give --poses FILE, TUM or KITTI)")
    imu_topic = _pick_topic(reader, opt.imu_topic, (IMU,), ("/imu", "/imu/data"), "IMU", root)
    if imu_topic is not None:
        seq.imu_roll_pitch = _imu_roll_pitch(reader, imu_topic, seq.times, base, edges, root)
    return seq


def _stamp_convention(seq: BagSequence, opt: BagOptions) -> None:
    """Whether a scan's stamp is its sweep's end (kept) or start (moved to the end, per-point times made
    <= 0): from ``--scan-stamp`` or from the first scans' per-point times."""
    if opt.scan_stamp not in (None, "start", "end"):
        raise InputError(f"--scan-stamp {opt.scan_stamp!r}: expected start or end")
    ends = []
    for k in range(min(3, len(seq))):
        _, rel = seq._decode(k)
        if rel is not None and len(rel) and np.ptp(rel) > 0:
            ends.append(float(np.max(rel)))
    seq._cache = None
    if not ends:
        seq.meta.setdefault("point_times", "none (no per-point time field: scans are not de-skewed)")
        return
    period = float(np.median(np.diff(seq.times))) if len(seq) > 1 else 0.1
    end = float(np.median(ends))
    start_stamped = opt.scan_stamp == "start" or (opt.scan_stamp is None and end > 0.1 * period)
    if start_stamped:
        seq.stamp_to_end_s = end
    seq.meta.setdefault("scan_stamp", "start" if start_stamped else "end")


def poses_at_scans(path: str | os.PathLike, times: np.ndarray) -> np.ndarray:
    """The LiDAR's poses at the scans from a file: KITTI (12 numbers a line, one line per scan) or TUM
    (``time x y z qx qy qz qw``, interpolated at the scans' times, which must lie within its span)."""
    path, n = Path(path), len(times)
    try:
        rows = [
            line.split()
            for line in path.read_text().splitlines()
            if line.strip() and not line.startswith("#")
        ]
    except OSError as err:
        raise InputError(f"{path}: cannot read poses ({err.strerror})") from None
    try:
        values = np.array([[float(v) for v in r] for r in rows], np.float64)
    except ValueError:
        raise InputError(
            f"{path}: poses must be numbers (KITTI: 12 a line; TUM: time x y z qx qy qz qw)"
        ) from None
    if values.ndim != 2 or values.shape[1] not in (8, 12) or not np.all(np.isfinite(values)):
        raise InputError(f"{path}: poses must be 12 (KITTI) or 8 (TUM) finite numbers a line")
    if values.shape[1] == 12:
        if len(values) != n:
            raise InputError(f"{path}: {len(values)} KITTI poses for {n} scans")
        P = np.tile(np.eye(4), (n, 1, 1))
        P[:, :3, :] = values.reshape(-1, 3, 4)
        return P
    P = np.array([_T(v[1:4], v[4:8]) for v in values])
    return _at(values[:, 0], P, times, f"poses file {path.name}", path)


def _imu_roll_pitch(reader, topic, times, base, edges, root) -> np.ndarray:
    cons = [c for c in reader.connections if c.topic == topic]
    stamps, R, frame = [], [], None
    use_orientation = True
    for con, _, raw in reader.messages(connections=cons):
        m = reader.deserialize(raw, con.msgtype)
        frame = frame or m.header.frame_id.lstrip("/")
        stamps.append(_stamp_s(m.header))
        if m.orientation_covariance[0] == -1:
            use_orientation = False
        if use_orientation:
            q = m.orientation
            R.append(matrix_from_quat(np.array([q.x, q.y, q.z, q.w])))
        else:  # gravity: the accelerometer's reading at rest points up in the body frame
            a = m.linear_acceleration
            g = np.array([a.x, a.y, a.z]) / max(np.linalg.norm([a.x, a.y, a.z]), 1e-9)
            roll, pitch = math.atan2(g[1], g[2]), math.atan2(-g[0], math.hypot(g[1], g[2]))
            R.append(_ry(pitch) @ _rx(roll))
    if not stamps:
        raise InputError(f"{root}: IMU topic {topic} has no messages")
    if frame and frame != base:
        T = _chain(edges, frame, base)  # T_imu_base
        if T is not None:
            R = [r @ T[:3, :3] for r in R]
    stamps = np.asarray(stamps)
    k = np.clip(np.searchsorted(stamps, times), 0, len(stamps) - 1)
    prev = np.clip(k - 1, 0, len(stamps) - 1)
    k = np.where(np.abs(stamps[prev] - times) < np.abs(stamps[k] - times), prev, k)
    out = np.empty((len(times), 2))
    for i, j in enumerate(k):
        r = R[j]
        out[i] = math.atan2(r[2, 1], r[2, 2]), -math.asin(max(-1.0, min(1.0, r[2, 0])))
    return out

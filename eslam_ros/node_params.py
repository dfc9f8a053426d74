"""The SLAM node's ROS parameters, and how they become an eslam_core configuration.

The node has two kinds of parameters:

- *Node settings* (`NodeSettings`): frames, QoS, synchronizer, output directory, publishing periods. Each field
  below names its ROS parameter (e.g. `sync.queue_size`) and says what it does.
- *ESLAM settings*: every leaf of `eslam_core.config.Config`, named `eslam.<section>.<key>`, e.g.
  `eslam.tracking.iterations` or `eslam.mapping.weights.depth`. `eslam.scene.bound` is the one list-valued key;
  ROS parameters cannot nest lists, so it is given flat: [xmin, ymin, zmin, xmax, ymax, zmax].

Where the ESLAM configuration comes from, later entries winning:
  1. the shipped preset named by `preset` (live, the default; fast, replica, tum, icl, scannet, demo), or, when
     `config_file` is set, that YAML file instead (it names its own base preset with `extends:`);
  2. every `eslam.*` parameter given in a parameter file or on the command line.
The node declares every `eslam.*` parameter with the value of step 1 as its default, so `ros2 param list / get`
shows the configuration actually in use. The result is validated by the configuration's own checks.

The functions here are pure (no rclpy), so they are usable and testable without a running node.
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Union

from eslam_core.config import MOVED_KEYS, Config, ConfigError, config_from_dict, load_config

ESLAM_PREFIX = "eslam."
# A value a ROS 2 parameter can hold (None = PARAMETER_NOT_SET).
ParamValue = Union[None, bool, int, float, str, list]
# Config keys whose value is [[x, y, z], [x, y, z]]: flat 6-number arrays as ROS parameters.
_BOX_KEYS = ("scene.bound",)

QOS_CHOICES = ("sensor_data", "reliable")
POLICY_CHOICES = ("live", "offline")
ODOM_SOURCES = ("auto", "topic", "tf")
POSE_FRAMES = ("camera", "base")


class NodeParameterError(ValueError):
    """A ROS parameter of the node has a wrong type or an impossible value; the message names it and the fix."""


def _param(default: Any, name: str, doc: str) -> Any:
    """A NodeSettings field: its default, its ROS parameter name and its description (`ros2 param describe`)."""
    return field(default=default, metadata={"param": name, "doc": doc})


@dataclass(frozen=True)
class NodeSettings:
    """What the node does around the SLAM core. Field metadata: ROS parameter name and description."""

    preset: str = _param("live", "preset", "eslam_core preset the configuration starts from (live: a 30 Hz camera on "
                                           "2 cores; fast: offline on a CPU; replica, tum, icl, scannet: the paper's "
                                           "settings; demo: the embedded synthetic room)")
    config_file: str = _param("", "config_file", "eslam_core YAML file used instead of `preset` (it may `extends:` "
                                                 "a preset); empty = use the preset")
    map_frame: str = _param("map", "map_frame", "frame_id of published poses, path and mesh (the first camera's "
                                                "optical frame, squared with the scene; in REP 105 mode odom_frame "
                                                "at the first frame)")
    output_dir: str = _param("eslam_output", "output_dir", "folder for saved trajectory, mesh and checkpoint "
                                                           "(services and shutdown; relative to the working "
                                                           "directory)")
    workers: int = _param(2, "workers", "SLAM runtime processes: 2 = tracking and mapping in parallel processes, "
                                        "1 = in-process")
    policy: str = _param("live", "policy", "live: track the oldest waiting frame while at most "
                                           "`runtime.live_backlog` (1) more wait, else skip to the newest, dropping "
                                           "(and counting) the others; "
                                           "offline: every frame in order (the node stops taking messages while "
                                           "SLAM is behind: use input_qos reliable and a deep input_queue_depth)")
    input_qos: str = _param("sensor_data", "input_qos", "QoS of the input subscriptions: sensor_data (best effort, "
                                                        "matches every publisher) or reliable")
    input_queue_depth: int = _param(30, "input_queue_depth", "history depth of the input subscriptions (30: a "
                                                             "second at 30 Hz, so a busy node counts the frames it "
                                                             "drops instead of losing them in DDS)")
    sync_queue_size: int = _param(10, "sync.queue_size", "messages kept per stream while pairing rgb and depth")
    sync_max_interval: float = _param(0.02, "sync.max_interval", "largest stamp difference (s) of a paired rgb and "
                                                                 "depth image; 0 = no limit")
    sync_age_penalty: float = _param(0.1, "sync.age_penalty", "message_filters' age penalty: larger pairs sooner, "
                                                              "slightly worse matches")
    sync_idle_flush: float = _param(0.5, "sync.idle_flush", "seconds without images after which the pending pair is "
                                                            "emitted (end of stream); 0 = never")
    depth_scale: float = _param(0.0, "depth_scale", "depth units per metre of the depth images; 0 = by encoding "
                                                    "(16UC1/mono16: 1000, 32FC1: 1)")
    mesh_period: float = _param(5.0, "mesh_period", "seconds between two map snapshots meshed for ~/mesh (only "
                                                     "changed blocks are published); 0 = no mesh on ~/mesh")
    mesh_resolution: float = _param(0.0, "mesh_resolution", "voxel size (m) of the published and saved meshes; "
                                                            "0 = eslam.mesh.resolution")
    mesh_triangle_budget: int = _param(100_000, "mesh_triangle_budget", "most triangles published on ~/mesh "
                                                                        "(above it every 2nd, 4th, ... triangle of "
                                                                        "each block)")
    mesh_block_size: float = _param(1.0, "mesh_block_size", "edge (m) of the world blocks ~/mesh is cut into (rounded "
                                                             "to a whole number of voxels): one marker per block, "
                                                             "re-sent only when its surface changed")
    mesh_time_budget: float = _param(0.5, "mesh_time_budget", "seconds of meshing per ~/mesh message: a large map is "
                                                              "meshed in pieces, changed blocks first")
    mesh_duty: float = _param(0.4, "mesh_duty", "most share of the time the mesh process works (after a job of t s "
                                                "it rests t * (1 / mesh_duty - 1) s): its work slows tracking")
    mesh_nice: int = _param(19, "mesh_nice", "nice value (0-19) of the mesh process: 19 = Linux's SCHED_IDLE, only CPU "
                                             "time that no other process wants")
    path_period: float = _param(1.0, "path_period", "seconds between ~/path publications")
    path_max_poses: int = _param(4096, "path_max_poses", "most poses in ~/path: a long run's path shows every 2nd, "
                                                         "4th, ... frame and the newest (its cost stays flat)")
    status_period: float = _param(1.0, "status_period", "seconds between ~/status publications")
    publish_tf: bool = _param(True, "publish_tf", "broadcast on /tf (camera mode: map_frame -> camera frame; REP 105 "
                                                  "mode: map_frame -> odom_frame) when tf2_ros or tf2_msgs can be "
                                                  "imported")
    tf_child_frame: str = _param("", "tf_child_frame", "camera mode: child frame of the TF and of ~/odom; empty = "
                                                       "the image header's frame_id")
    log_throttle: float = _param(5.0, "log_throttle", "seconds between two log lines about the same kind of "
                                                      "skipped frame")
    time_jump_reset: float = _param(1.0, "time_jump_reset", "a stamp this many seconds older than the last one "
                                                            "starts a new stream and resets the map (a bag "
                                                            "looped); 0 = never reset, skip such frames")
    map_file: str = _param("", "map_file", "a checkpoint.pt (saved by ~/save_checkpoint or eslam run) the map starts "
                                           "from, at start and on ~/load_map; the camera starts lost and is "
                                           "relocalized; with eslam.run.mode localization the map is not changed")
    save_on_shutdown: bool = _param(True, "save_on_shutdown", "save trajectory, mesh and checkpoint to output_dir "
                                                              "on Ctrl-C / SIGTERM (and on lifecycle cleanup / "
                                                              "shutdown)")
    start_queue_bytes: int = _param(512 * 2**20, "start_queue_bytes", "offline policy: bytes of frames kept while "
                                                                      "the SLAM runtime starts (512 MiB: ~250 frames "
                                                                      "of 640x480; beyond it the oldest are dropped "
                                                                      "and counted); the live policy keeps the "
                                                                      "newest 30")
    # ---- the robot's TF tree (REP 105) and external odometry
    odom_frame: str = _param("", "odom_frame", "the robot's odometry frame (e.g. odom); with base_frame set the node "
                                               "publishes map_frame -> odom_frame (REP 105) instead of map_frame -> "
                                               "camera, and takes the odometry as its motion prior")
    base_frame: str = _param("", "base_frame", "the robot's base frame (e.g. base_link), the child of odom_frame in "
                                               "the odometry")
    odom_source: str = _param("auto", "odom_source", "where odom_frame -> base_frame comes from: tf, topic (a "
                                                     "nav_msgs/Odometry on `odom`), or auto (tf when tf2_ros is "
                                                     "installed, else topic)")
    base_to_camera: tuple = _param((), "base_to_camera", "[x, y, z, qx, qy, qz, qw]: pose of the camera's optical "
                                                         "frame (the image frame_id) in base_frame; empty = from TF "
                                                         "(write floats, 0.0 not 0: a ROS array holds one type)")
    pose_frame: str = _param("camera", "pose_frame", "whose pose ~/pose, ~/odom and ~/path give: camera (the image "
                                                     "frame_id) or base (base_frame)")
    odom_wait: float = _param(0.1, "odom.wait", "seconds of images (stamps) a frame waits for the odometry at its "
                                                "stamp once the odometry stalled, before it goes on without (counted "
                                                "in odom_missing); at the end of a stream, this plus 1 s of wall "
                                                "time; while odometry flows, up to 1 s of images")
    odom_max_gap: float = _param(0.5, "odom.max_gap", "seconds between two odometry samples beyond which a frame "
                                                      "between them gets no odometry (counted in odom_gaps)")
    odom_max_speed: float = _param(5.0, "odom.max_speed", "m/s; odometry moving faster between two frames is a jump "
                                                          "(counted in odom_jumps; SLAM gets it without the jump)")
    odom_max_angular_speed: float = _param(6.0, "odom.max_angular_speed", "rad/s; odometry turning faster between "
                                                                          "two frames is a jump")
    # ---- diagnostics (~/status and /diagnostics)
    diagnostics_hardware_id: str = _param("eslam", "diagnostics.hardware_id", "hardware_id of the node's "
                                                                              "DiagnosticStatus")
    no_input_timeout: float = _param(5.0, "diagnostics.no_input_timeout", "seconds without an rgb-depth pair (or, "
                                                                          "with odom_source topic, odometry) before "
                                                                          "the status warns; 0 = never")
    min_input_rate: float = _param(0.0, "diagnostics.min_input_rate", "Hz; a lower rate of rgb-depth pairs (over "
                                                                      "the last 5 s) warns; 0 = never")

    def validate(self) -> "NodeSettings":
        def check(ok: bool, attribute: str, message: str) -> None:
            if not ok:
                name = _FIELD_TO_PARAM[attribute]
                raise NodeParameterError(
                    f"ROS parameter '{name}' = {getattr(self, attribute)!r}: {message} (set it in the parameter "
                    f"file or with --ros-args -p {name}:=...)"
                )

        check(self.workers >= 1, "workers", "must be >= 1")
        check(self.policy in POLICY_CHOICES, "policy", f"must be one of {', '.join(POLICY_CHOICES)}")
        check(self.input_qos in QOS_CHOICES, "input_qos", f"must be one of {', '.join(QOS_CHOICES)}")
        check(self.input_queue_depth >= 1, "input_queue_depth", "must be >= 1")
        check(self.sync_queue_size >= 1, "sync_queue_size", "must be >= 1")
        check(self.map_frame.strip() != "", "map_frame", "must be a frame name such as 'map'")
        check(self.output_dir.strip() != "", "output_dir", "must name a folder")
        for attribute in ("sync_max_interval", "sync_age_penalty", "sync_idle_flush", "depth_scale", "mesh_period",
                          "mesh_resolution", "log_throttle", "time_jump_reset"):
            value = getattr(self, attribute)
            check(math.isfinite(value) and value >= 0, attribute, "must be a number >= 0")
        for attribute in ("path_period", "status_period"):
            value = getattr(self, attribute)
            check(math.isfinite(value) and value > 0, attribute, "must be a positive number of seconds")
        check(self.mesh_triangle_budget >= 1, "mesh_triangle_budget", "must be >= 1")
        check(self.path_max_poses >= 2, "path_max_poses", "must be >= 2 (the first and the newest pose)")
        check(math.isfinite(self.mesh_block_size) and self.mesh_block_size > 0, "mesh_block_size",
              "must be a positive number of metres")
        check(math.isfinite(self.mesh_time_budget) and self.mesh_time_budget > 0, "mesh_time_budget",
              "must be a positive number of seconds")
        check(math.isfinite(self.mesh_duty) and 0 < self.mesh_duty <= 1, "mesh_duty",
              "must be a share of the time, in (0, 1]")
        check(0 <= self.mesh_nice <= 19, "mesh_nice", "must be a nice value from 0 to 19")
        check(self.start_queue_bytes >= 0, "start_queue_bytes", "must be >= 0")
        check(bool(self.odom_frame.strip()) == bool(self.base_frame.strip()),
              "odom_frame" if not self.odom_frame.strip() else "base_frame",
              "odom_frame and base_frame are set together (both empty: publish map_frame -> camera)")
        frames = [f for f in (self.map_frame, self.odom_frame, self.base_frame) if f]
        check(len(set(frames)) == len(frames), "odom_frame", "map_frame, odom_frame and base_frame must differ")
        check(self.odom_source in ODOM_SOURCES, "odom_source", f"must be one of {', '.join(ODOM_SOURCES)}")
        check(len(self.base_to_camera) in (0, 7) and all(math.isfinite(v) for v in self.base_to_camera)
              and (not self.base_to_camera or math.hypot(*self.base_to_camera[3:]) > 1e-6), "base_to_camera",
              "must be empty (from TF) or 7 numbers [x, y, z, qx, qy, qz, qw] with a non-zero quaternion")
        check(self.pose_frame in POSE_FRAMES, "pose_frame", f"must be one of {', '.join(POSE_FRAMES)}")
        check(self.pose_frame == "camera" or bool(self.base_frame), "pose_frame",
              "'base' needs base_frame (and odom_frame) to be set")
        for attribute in ("odom_wait", "no_input_timeout", "min_input_rate"):
            value = getattr(self, attribute)
            check(math.isfinite(value) and value >= 0, attribute, "must be a number >= 0")
        for attribute in ("odom_max_gap", "odom_max_speed", "odom_max_angular_speed"):
            value = getattr(self, attribute)
            check(math.isfinite(value) and value > 0, attribute, "must be a positive number")
        return self

    @property
    def rep105(self) -> bool:
        """odom_frame and base_frame are set: publish map -> odom and use the odometry."""
        return bool(self.odom_frame)


_FIELD_TO_PARAM = {f.name: f.metadata["param"] for f in dataclasses.fields(NodeSettings)}


def node_parameter_defaults() -> dict[str, tuple[Any, str]]:
    """{ROS parameter name: (default value, description)} of every node setting."""
    # tuples are ROS arrays, declared as lists
    return {f.metadata["param"]: (list(f.default) if isinstance(f.default, tuple) else f.default, f.metadata["doc"])
            for f in dataclasses.fields(NodeSettings)}


def settings_from_parameters(values: Mapping[str, Any]) -> NodeSettings:
    """NodeSettings from {ROS parameter name: value}; missing names keep their defaults.

    Types are checked here rather than by rclpy, so that `mesh_period: 5` (an integer) is accepted where a float
    is expected and a wrong type gets a message naming the parameter.
    """
    kwargs = {}
    for f in dataclasses.fields(NodeSettings):
        name = f.metadata["param"]
        if name not in values or values[name] is None:
            continue
        kwargs[f.name] = _typed(values[name], type(f.default), name)
    return NodeSettings(**kwargs).validate()


def _typed(value: Any, expected: type, name: str) -> Any:
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected is tuple:  # an array of numbers
        if isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                    for v in value):
            return tuple(float(v) for v in value)
        raise NodeParameterError(
            f"ROS parameter '{name}' must be a list of numbers, got {value!r}; write it as [0.1, 0.0, ...] (floats "
            f"with a decimal point) in the parameter file or the -p {name}:=... argument"
        )
    if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
        raise NodeParameterError(
            f"ROS parameter '{name}' must be of type {expected.__name__}, got {value!r} "
            f"({type(value).__name__}); fix the parameter file or the -p {name}:=... argument"
        )
    return value


# ------------------------------------------------------------------------------------------ ESLAM configuration


def base_config(settings: NodeSettings) -> Config:
    """The configuration before any eslam.* parameter: the config file if one is set, else the preset."""
    if settings.config_file:
        path = Path(settings.config_file).expanduser()
        if not path.is_file():
            raise ConfigError(
                f"ROS parameter 'config_file' names {path}, which does not exist; give the path of an eslam_core "
                f"YAML file, or leave it empty to use the preset '{settings.preset}'"
            )
        return load_config(path)
    return load_config(settings.preset)


def config_parameters(cfg: Config) -> dict[str, ParamValue]:
    """{`eslam.<section>.<key>`: value} of every leaf of `cfg`, in values a ROS parameter can hold."""
    flat: dict[str, ParamValue] = {}
    _flatten(dataclasses.asdict(cfg), "", flat)
    return {ESLAM_PREFIX + key: value for key, value in flat.items()}


def _flatten(node: Mapping[str, Any], prefix: str, out: dict[str, ParamValue]) -> None:
    for name, value in node.items():
        key = prefix + name
        if isinstance(value, dict):
            _flatten(value, key + ".", out)
        elif key in _BOX_KEYS and value is not None:
            out[key] = [float(v) for corner in value for v in corner]
        else:
            out[key] = value


def config_from_parameters(values: Mapping[str, ParamValue], source: str) -> Config:
    """Config from {`eslam.<section>.<key>`: value} of every leaf (as `config_parameters` names them).

    `source` names where the values came from, for the configuration's error messages.
    """
    nested: dict[str, Any] = {}
    for name, value in values.items():
        if not name.startswith(ESLAM_PREFIX):
            raise NodeParameterError(f"'{name}' is not an ESLAM parameter: their names start with '{ESLAM_PREFIX}'")
        key = name[len(ESLAM_PREFIX):]
        if key in _BOX_KEYS and value is not None:
            value = _box(value, name)
        node = nested
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = list(value) if isinstance(value, (list, tuple)) else value
    return config_from_dict(nested, source)


def _box(value: Any, name: str) -> list[list[float]]:
    numbers = list(value) if isinstance(value, (list, tuple)) else []
    if len(numbers) != 6 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
        raise NodeParameterError(
            f"ROS parameter '{name}' must be 6 numbers [xmin, ymin, zmin, xmax, ymax, zmax] (metres), got {value!r}"
        )
    return [[float(v) for v in numbers[:3]], [float(v) for v in numbers[3:]]]


def unknown_eslam_parameters(given: Mapping[str, Any], cfg: Config) -> list[str]:
    """Names among `given` that start with `eslam.` but are no configuration key (typos would be ignored)."""
    known = set(config_parameters(cfg))
    return sorted(name for name in given if name.startswith(ESLAM_PREFIX) and name not in known)


def unknown_parameter_error(name: str, cfg: Config) -> NodeParameterError:
    """The error for an `eslam.*` parameter that names no configuration key, listing its section's keys (or the
    key's new name, for a key that moved to another section)."""
    parts = name[len(ESLAM_PREFIX):].split(".")
    moved = MOVED_KEYS.get((parts[0], parts[1])) if len(parts) >= 2 else None
    if moved is not None:
        new = ESLAM_PREFIX + ".".join([moved] + parts[2:])
        return NodeParameterError(f"ESLAM parameter '{name}' is now '{new}' (each section of the config belongs to "
                                  f"the part that reads it); rename it in the parameter file")
    section = name.rsplit(".", 1)[0] + "."
    siblings = sorted(k[len(section):] for k in config_parameters(cfg) if k.startswith(section))
    hint = f"known keys of {section[:-1]}: {', '.join(siblings)}" if siblings else (
        "sections: " + ", ".join(sorted({k.split('.')[1] for k in config_parameters(cfg)})))
    return NodeParameterError(f"unknown ESLAM parameter '{name}' ({hint}); fix the parameter file")


def check_odometry_mode(settings: NodeSettings, cfg: Config) -> None:
    """tracking.mode 'external' takes every pose from the odometry, so the node needs one."""
    if cfg.tracking.mode == "external" and not settings.rep105:
        raise NodeParameterError(
            "eslam.tracking.mode 'external' takes the poses from the robot's odometry: set odom_frame and base_frame "
            "(and odom_source / base_to_camera), or use eslam.tracking.mode:=track"
        )


def resolve_config(settings: NodeSettings, overrides: Mapping[str, ParamValue]) -> Config:
    """The node's configuration: `base_config(settings)` with `overrides` (eslam.* parameter values) applied."""
    base = base_config(settings)
    unknown = unknown_eslam_parameters(overrides, base)
    if unknown:
        raise unknown_parameter_error(unknown[0], base)
    values = config_parameters(base)
    values.update(overrides)
    origin = f"config file {settings.config_file}" if settings.config_file else f"preset '{settings.preset}'"
    return config_from_parameters(values, f"ROS parameters eslam.* over {origin}")


# ------------------------------------------------------------------------------------------ docs/ros.md's tables


def node_settings_markdown() -> str:
    """docs/ros.md's table of the node settings: every NodeSettings field, its default and its description."""
    rows = ["| parameter | default | meaning |", "|---|---|---|"]
    for name, (default, doc) in node_parameter_defaults().items():
        doc = re.sub(r"(?<![`\w])(~/\w+|/tf\b)", r"`\1`", doc)  # topic names as code (a lone ~ is strikethrough)
        rows.append(f"| `{name}` | `{_yaml_text(default)}` | {doc} |")
    return "\n".join(rows)


def eslam_keys_markdown() -> str:
    """docs/ros.md's list of the `eslam.<section>.<key>` parameters: every key of eslam_core's Config by section."""
    rows, cfg = ["| section | keys |", "|---|---|"], Config()
    for f in dataclasses.fields(cfg):
        section = getattr(cfg, f.name)
        if not dataclasses.is_dataclass(section):
            rows.append(f"| (top level) | `{f.name}` |")
            continue
        keys = []
        for key in dataclasses.fields(section):
            value = getattr(section, key.name)
            keys.append(f"{key.name}.{{{','.join(k.name for k in dataclasses.fields(value))}}}"
                        if dataclasses.is_dataclass(value) else key.name)
        rows.append(f"| {f.name} | `{' '.join(keys)}` |")
    return "\n".join(rows)


MARKDOWN_TABLES = {"node": node_settings_markdown, "eslam": eslam_keys_markdown}


def _yaml_text(value: Any) -> str:
    """A default as a parameter file writes it: "text", true, 0.5, [0.1, 0.0]."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml_text(v) for v in value) + "]"
    return repr(value)


if __name__ == "__main__":  # python -m eslam_ros.node_params --markdown node|eslam
    import argparse

    parser = argparse.ArgumentParser(description="print a table of docs/ros.md, generated from the code")
    parser.add_argument("--markdown", choices=sorted(MARKDOWN_TABLES), required=True,
                        help="node: the node settings (NodeSettings); eslam: the eslam.* keys by section (Config)")
    print(MARKDOWN_TABLES[parser.parse_args().markdown]())

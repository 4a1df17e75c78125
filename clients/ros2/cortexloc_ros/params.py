"""The node's parameters: each declared with its default and description (`PARAMETERS`, one home; the
YAML in config/params.yaml and the README list the same), read into a checked `Config`.

Bad values are all reported at once, before anything is subscribed or posted (`ConfigError`): the node
exits with status 2 and one line per problem. The API key is never a parameter (a parameter shows on the
command line, in `ros2 param get` and in launch logs): it comes from the environment variable that
`api_key_env` names, or from the file `api_key_file` names.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import textwrap
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from cortexloc_client import MAX_TOP_K, STREAM_PATTERN
from cortexloc_ros.core import DROP_POLICIES

__all__ = ["PARAMETERS", "Config", "ConfigError", "config_warnings", "empty_overrides", "read_config",
           "stream_problem", "trail_of", "usage"]

#: name -> (default, description). Nested names (`rate.every_n`) are YAML sections.
PARAMETERS: dict[str, tuple[Any, str]] = {
    "service_url": ("http://127.0.0.1:8000", "the cortexloc service, http(s)://host:port"),
    "api_key_env": ("CORTEXLOC_API_KEY", "name of the environment variable that holds the service's API key "
                    "(unset or empty: no key); the key itself is never a parameter"),
    "api_key_file": ("", "a file whose first line is the API key (read at start; wins over api_key_env)"),
    "map": ("default", "the map posted to; created with the service's defaults when missing at start and "
            "learn is true (a map deleted while the node runs is an error, never created again)"),
    "stream": ("", "the stream (one per camera); empty: the image topic's resolved name without its "
               "leading '/'"),
    "trail": ("", "the robot's trail (service `metadata.trail`): streams naming one trail share one "
              "short-term memory, so a robot with two cameras, or a renamed node, closes no loop on its own "
              "recent path; empty: the node's namespace without its leading '/' (none at the root "
              "namespace: the stream's own trail)"),
    "learn": (True, "true: map (frames are learned and stored; loop closure while mapping); false: localise "
              "(nothing stored changes)"),
    "top_k": (5, f"frame-level matches in each answer (0 or more; over {MAX_TOP_K}, the service's default "
              f"CORTEXLOC_MAX_TOP_K, a warning at start)"),
    "run_id": ("", "this drive's id, part of each post's Idempotency-Key (run id + topic + stamp + a "
               "CRC-32 of the image); empty: a new one per start, a new drive (the stream's context on the "
               "service is reset at start), so a bag replayed twice is two drives. Set it to resume one "
               "drive (its context kept)"),
    "retractions_poll": (5.0, "seconds between reads of the map's loop-closure log for retractions of this "
                         "stream's closures (an operator's repair withdrew them), each published on "
                         "topics.loop_closures with the id of the closure it withdraws; 0: off"),
    "request_timeout": (10.0, "seconds to connect and between bytes of a reply; a post cut short is retried "
                        "with the same key"),
    "image_transport": ("raw", "raw: sensor_msgs/Image on topics.image; compressed: sensor_msgs/"
                        "CompressedImage on topics.image + '/compressed' (JPEG or PNG, posted as it is)"),
    "odom_tolerance": (0.05, "seconds: a frame takes the odometry pose nearest its stamp within this, once "
                       "one at or after its stamp is in (it waits for that at most this + 50 ms)"),
    "camera_mount": ([0.0, 0.0, 0.0], "the camera's planar mounting on the odometry's child frame: x, y "
                     "(metres), yaw (radians), in place of tf; the pose sent is the camera's"),
    "place_covariance": ([1.0, 1.0, 0.1], "variances of x, y (m^2) and yaw (rad^2) published with the "
                         "place's stored pose (the answer names a stored frame, not a metric estimate); "
                         "z, roll and pitch get 1e6 (a planar pose)"),
    "rate.every_n": (1, "post every Nth frame of the camera (1: every frame)"),
    "rate.min_distance": (0.0, "metres: post a frame only once the camera moved this far since the last "
                          "frame posted (0: off; needs odometry)"),
    "queue.size": (10, "frames waiting to be posted, at most; a full queue drops by queue.policy"),
    "queue.policy": ("drop_oldest", "drop_oldest: the newest frames are kept (localising); drop_newest: "
                     "frames arriving at a full queue are dropped"),
    "topics.image": ("camera/image_raw", "the camera's image topic"),
    "topics.camera_info": ("camera/camera_info", "the camera's intrinsics for geometric verification "
                           "(empty: none)"),
    "topics.odometry": ("", "nav_msgs/Odometry giving each frame's pose (empty: frames carry no pose)"),
    "topics.place": ("cortexloc/place", "std_msgs/String: each answer as JSON (README, 'With ROS 2')"),
    "topics.place_pose": ("cortexloc/place_pose", "geometry_msgs/PoseWithCovarianceStamped: the matched "
                          "place's stored pose, stamped with the frame's stamp"),
    "topics.loop_closures": ("cortexloc/loop_closures", "std_msgs/String: each loop closure as JSON"),
    "topics.markers": ("cortexloc/loop_closure_markers", "visualization_msgs/MarkerArray: loop-closure "
                       "edges for RViz"),
    "topics.diagnostics": ("/diagnostics", "diagnostic_msgs/DiagnosticArray at 1 Hz"),
}

#: The service's map ids (storage/catalog.py MAP_ID_RE).
_MAP_ID = re.compile(r"^[a-z0-9][a-z0-9._-]{0,63}$")
_RUN_ID = re.compile(r"^[A-Za-z0-9_-]{1,40}$")
#: The service's stream (and trail) names, as the client states them (service/schemas.py STREAM_PATTERN).
_STREAM = re.compile(STREAM_PATTERN)


class ConfigError(ValueError):
    """Parameters the node cannot run with; `problems` has one line each."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("bad parameters:\n" + "\n".join(f"  - {p}" for p in problems))
        self.problems = problems


@dataclass(frozen=True)
class Config:
    """The checked parameters (`PARAMETERS` says what each is)."""

    service_url: str
    api_key: str | None
    map_id: str
    stream: str
    trail: str
    learn: bool
    top_k: int
    run_id: str
    resume: bool  # `run_id` was given: this start resumes that drive (its stream context is kept)
    request_timeout: float
    retractions_poll: float  # seconds; 0: no retraction follower
    compressed: bool
    odom_tolerance_ns: int
    camera_mount: tuple[float, float, float]
    place_covariance: tuple[float, float, float]
    every_n: int
    min_distance: float
    queue_size: int
    queue_policy: str
    topics: dict[str, str]


def usage(prog: str = "cortexloc-ros") -> str:
    """What `--help` prints: how to run the node and every parameter with its default and description."""
    lines = [f"usage: {prog} [--ros-args -p name:=value ... --params-file params.yaml]",
             "",
             "cortexloc_node: camera frames (and odometry, camera_info) in, places and loop closures out,",
             "through the cortexloc service. Parameters (bad values exit 2 with one line each):", ""]
    for name, (default, description) in PARAMETERS.items():
        shown = "''" if default == "" else str(default).lower() if isinstance(default, bool) else default
        lines.append(f"  {name} (default {shown})")
        lines.append(textwrap.fill(description, 100, initial_indent=" " * 6, subsequent_indent=" " * 6))
    lines += ["", "Topics, messages and diagnostics: the package's README.md (clients/ros2/README.md); the "
              "defaults as YAML: config/params.yaml."]
    return "\n".join(lines)


def _api_key(env_name: str, file_name: str, problems: list[str]) -> str | None:
    if file_name:
        try:
            return Path(file_name).expanduser().read_text().splitlines()[0].strip() or None
        except (OSError, IndexError, UnicodeDecodeError) as e:
            problems.append(f"api_key_file: cannot read a key from {file_name!r} ({e.__class__.__name__})")
            return None
    return os.environ.get(env_name) or None if env_name else None


def _kind(default: Any) -> str:
    if isinstance(default, bool):
        return "true or false"
    if isinstance(default, int):
        return "an integer"
    if isinstance(default, float):
        return "a number"
    return "a string" if isinstance(default, str) else "a list of numbers"


def _number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _typed(values: dict[str, Any], problems: list[str]) -> dict[str, Any]:
    """The values in their declared types (an integer where a number is due is taken as one); a line in
    `problems` for each that is of another type (parameters are declared with dynamic typing so that
    this says which and why)."""
    out: dict[str, Any] = {}
    for name, (default, _) in PARAMETERS.items():
        value = values[name]
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif isinstance(default, float):
            ok = _number(value)
            value = float(value) if ok else value
        elif isinstance(default, str):
            ok = isinstance(value, str)
        else:
            ok = (not isinstance(value, str | bytes) and hasattr(value, "__iter__")
                  and all(map(_number, value)))
            value = [float(x) for x in value] if ok else value
        if not ok:
            problems.append(f"{name}: {value!r} is not {_kind(default)}")
        out[name] = value
    return out


def stream_problem(name: str, value: str) -> str | None:
    """The line saying why `value` (the parameter `name`'s) is not a stream name the service takes, or
    None: the service refuses such a name on every frame, so the node refuses it at start."""
    if _STREAM.fullmatch(value):  # fullmatch: `$` also matches before a last newline
        return None
    return (f"{name}: {value!r} is not a stream name (up to 8 '/'-separated parts of 1 to 64 letters, "
            f"digits, '.', '_' or '-')")


def trail_of(trail: str, namespace: str) -> str | None:
    """The trail a node's frames name (`metadata.trail`): the `trail` parameter, else the node's namespace
    without its leading '/' (a robot's nodes share its namespace), else None (the root namespace: each
    stream its own trail)."""
    name = trail or namespace.strip("/")
    return name if name and _STREAM.fullmatch(name) else None


def config_warnings(cfg: Config) -> list[str]:
    """What the node says at start of values a service may refuse: a `top_k` over the service's default
    limit (an operator may raise `CORTEXLOC_MAX_TOP_K`, so it is no error here; where the limit is the
    default, every frame is refused 400 and counted in diagnostics as refused)."""
    if cfg.top_k > MAX_TOP_K:
        return [f"top_k: {cfg.top_k} is over {MAX_TOP_K}, the service's default CORTEXLOC_MAX_TOP_K: a "
                f"service that keeps that limit refuses every frame (400; diagnostics: refused)"]
    return []


def _url_problems(url: str) -> list[str]:
    """`service_url`'s problem: not http(s)://host[:port], or a port out of range (urlsplit says so only
    when `.port` is read; unchecked, the node would retry a URL no request can reach forever)."""
    parts = urlsplit(url)
    try:
        port_ok = parts.port is None or parts.port > 0
    except ValueError:
        port_ok = False
    if parts.scheme not in ("http", "https") or not parts.hostname:
        return [f"service_url: {url!r} is not an http(s)://host[:port] URL"]
    return [] if port_ok else [f"service_url: {url!r} has no port 1-65535"]


def _number_problems(v: dict[str, Any]) -> list[str]:
    """The float parameters' problems: each finite (a NaN passes every comparison, and is then refused
    by the service on every frame or published as it is), and within its documented range."""
    problems = []
    for name, positive, unit in (("request_timeout", True, "seconds"), ("odom_tolerance", True, "seconds"),
                                 ("rate.min_distance", False, "metres"),
                                 ("retractions_poll", False, "seconds")):
        value = v[name]
        if not (math.isfinite(value) and (value > 0 if positive else value >= 0)):
            problems.append(f"{name}: {value} must be a finite number {'> 0' if positive else '>= 0'} {unit}")
    for name, what in (("camera_mount", "x, y, yaw"), ("place_covariance", "variances of x, y, yaw")):
        values = list(v[name])
        if len(values) != 3:
            problems.append(f"{name}: {values} must be 3 numbers ({what})")
        elif not all(map(math.isfinite, values)):
            problems.append(f"{name}: {values} must be 3 finite numbers ({what})")
        elif name == "place_covariance" and any(c < 0 for c in values):
            problems.append(f"{name}: {values} holds a negative variance")
    return problems


def empty_overrides(argv: list[str]) -> list[str]:
    """A line for each `-p name:=` with nothing after `:=` among the ROS arguments: rcl cannot parse it
    and `rclpy.init` would end the node in a traceback; an empty string is `-p "name:=''"`."""
    ros = argv[argv.index("--ros-args") + 1:] if "--ros-args" in argv else []
    rules = [b for a, b in itertools.pairwise(ros) if a in ("-p", "--param")]
    return [f"{rule[:-2]}: -p {rule} gives no value (an empty string is -p \"{rule}''\")"
            for rule in rules if rule.endswith(":=") and len(rule) > 2]


def read_config(values: dict[str, Any], *, unknown: list[str] | None = None) -> Config:
    """Check the parameters' values (name -> value, as declared) and build the `Config`.

    Args:
        unknown: parameter names given that the node does not declare (a typo, or `api_key`).

    Raises:
        ConfigError: every problem found, one line each.
    """
    problems: list[str] = []
    v = _typed(values, problems)
    for name in unknown or []:
        if "api_key" in name and name not in PARAMETERS:
            problems.append(f"{name}: the API key is never a parameter (it would show on the command line); "
                            f"put it in the environment variable api_key_env names, or in api_key_file")
        else:
            problems.append(f"{name}: no such parameter (known: {', '.join(PARAMETERS)})")
    if problems:
        raise ConfigError(problems)
    problems += _url_problems(str(v["service_url"]))
    if not _MAP_ID.fullmatch(v["map"]):
        problems.append(f"map: {v['map']!r} is not a map id (a lower-case letter or digit, then up to "
                        f"63 of those, '.', '_', '-')")
    if v["top_k"] < 0:
        problems.append(f"top_k: {v['top_k']} must be 0 or more")
    if v["run_id"] and not _RUN_ID.fullmatch(v["run_id"]):
        problems.append(f"run_id: {v['run_id']!r} must be 1 to 40 letters, digits, '_' or '-'")
    for name in ("stream", "trail"):  # empty: derived by the node (the image topic; the namespace)
        problem = stream_problem(name, v[name]) if v[name] else None
        if problem:
            problems.append(problem)
    if v["image_transport"] not in ("raw", "compressed"):
        problems.append(f"image_transport: {v['image_transport']!r} is neither 'raw' nor 'compressed'")
    problems += _number_problems(v)
    if v["rate.every_n"] < 1:
        problems.append(f"rate.every_n: {v['rate.every_n']} must be >= 1")
    if v["rate.min_distance"] > 0 and not v["topics.odometry"]:
        problems.append("rate.min_distance needs odometry: set topics.odometry")
    if v["queue.size"] < 1:
        problems.append(f"queue.size: {v['queue.size']} must be >= 1")
    if v["queue.policy"] not in DROP_POLICIES:
        problems.append(f"queue.policy: {v['queue.policy']!r} is not one of {', '.join(DROP_POLICIES)}")
    for name in ("topics.image", "topics.place", "topics.place_pose", "topics.loop_closures",
                 "topics.markers", "topics.diagnostics"):
        if not v[name]:
            problems.append(f"{name}: must name a topic")
    api_key = _api_key(v["api_key_env"], v["api_key_file"], problems)
    if problems:
        raise ConfigError(problems)
    topics = {k.split(".", 1)[1]: val for k, val in v.items() if k.startswith("topics.")}
    return Config(service_url=str(v["service_url"]).rstrip("/"), api_key=api_key, map_id=v["map"],
                  stream=v["stream"], trail=v["trail"], learn=bool(v["learn"]), top_k=int(v["top_k"]),
                  run_id=v["run_id"] or uuid.uuid4().hex[:12], resume=bool(v["run_id"]),
                  request_timeout=float(v["request_timeout"]), retractions_poll=float(v["retractions_poll"]),
                  compressed=v["image_transport"] == "compressed",
                  odom_tolerance_ns=round(float(v["odom_tolerance"]) * 1e9),
                  camera_mount=tuple(map(float, v["camera_mount"])),  # type: ignore[arg-type]
                  place_covariance=tuple(map(float, v["place_covariance"])),  # type: ignore[arg-type]
                  every_n=int(v["rate.every_n"]), min_distance=float(v["rate.min_distance"]),
                  queue_size=int(v["queue.size"]), queue_policy=v["queue.policy"], topics=topics)

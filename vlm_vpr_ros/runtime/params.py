"""Parameter schema of ``vlm_vpr_node`` and its validation (pure: no ROS imports).

Every parameter is a field of :class:`NodeConfig` with its default, a one-line description, an
optional range and choices (:data:`PARAMETER_SPECS`); the node declares each one once from this
schema with a ``ParameterDescriptor`` (type, description, range, read-only), so ``ros2 param
describe`` and docs/node.md show the same text. Parameters marked ``writable`` may change at
runtime (``ros2 param set``; :data:`RUNTIME_WRITABLE`), validated by the same :func:`from_params`;
the others are structural and :func:`refusal_reason` says how to change them. Provider settings are
nested under ``prior.`` (``prior.base_url``, ``prior.model``, ``prior.lat`` ...), descriptor
options under ``descriptor_options.`` and the options of verification's learned local features and
matcher under ``feature_options.`` / ``matcher_options.`` (``weights`` paths, ``device``); all are
passed through to the registries, which reject unknown keys. Unknown top-level names and wrongly
typed values raise :class:`ConfigError`.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import math
import os
from dataclasses import dataclass, field
from typing import Any, Mapping

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.localizer import FUSION_MODES, LocalizerConfig
from vlm_vpr_ros.localization.verification.presets import PRESETS
from vlm_vpr_ros.localization.verification.stage import VerificationConfig
from vlm_vpr_ros.localization.verification.status import FALLBACK_STATUS, MAX_SIGMA_M, StatusPolicy
from vlm_vpr_ros.priors import available_prior_providers
from vlm_vpr_ros.runtime.worker import MODES

QOS_CHOICES = ("sensor_data", "best_effort", "reliable")
DURABILITY = ("volatile", "transient_local")
POSE_FRAMES = ("utm", "local_enu", "none")
POSE_ON = ("relocalize", "every_fix")
NESTED = ("prior", "descriptor_options", "feature_options", "matcher_options")
TOPIC_KINDS = ("navsat", "pose", "odometry")
PRIOR_ORDERS = ("topic_first", "provider_first")
#: parameters every rclpy node has
ROS_STANDARD = frozenset({"use_sim_time", "start_type_description_service"})


def _p(default: Any, doc: str, lo: float | None = None, hi: float | None = None,
       choices: tuple[str, ...] | None = None, writable: bool = False) -> Any:
    """A parameter field: default, description, inclusive range [lo, hi], string choices;
    ``writable``: may change at runtime (takes effect on the next query)."""
    return field(default=default, metadata={"doc": doc, "range": (lo, hi) if lo is not None
                                            else None, "choices": choices,
                                            "writable": writable})


@dataclass(frozen=True)
class ParamSpec:
    """What the node declares for one parameter (read by ``node.py``; no ROS types here)."""

    name: str
    default: Any
    doc: str
    kind: str  # "bool", "int", "float" or "str"
    range: tuple[float, float] | None = None  # inclusive
    choices: tuple[str, ...] | None = None
    read_only: bool = True  # structural: read once at start-up (configure), changes refused


@dataclass(frozen=True)
class NodeConfig:
    map_dir: str = _p("", "map folder built by `vlm-vpr build-map` (required)")
    descriptor: str = _p("", "descriptor name; must match the map's ('' = the map's own)")
    verify_map: bool = _p(False, "check the sha256 of every map file at start and on "
                                 "map_reload (slow for large maps; the manifest, sizes and "
                                 "content fingerprints are always checked)")
    prior_provider: str = _p("none", "prior source: none, fixed, recorded, answers, openai; "
                                     "settings under prior.*")
    prior_timeout_s: float = _p(30.0, "longest wait for a prior; then a flagged global fix",
                                0.001, 3600.0, writable=True)
    # the robot's own estimate as a prior (vlm_vpr_ros/priors/robot.py, docs/node.md)
    prior_topic: str = _p("", "the robot's own estimate as a prior: a topic with a NavSatFix, "
                              "PoseWithCovarianceStamped or Odometry (prior_topic_type; '' = "
                              "off); sigma from its covariance, grown with age")
    prior_topic_type: str = _p("navsat", "message type of prior_topic: navsat, pose or "
                                         "odometry (pose/odometry: in the pose_frame the node "
                                         "publishes, utm with a fixed utm_zone or local_enu)",
                               choices=TOPIC_KINDS)
    prior_topic_growth_m_per_s: float = _p(1.0, "prior_topic: sigma grows this many metres per "
                                                "second of the estimate's age", 0.0, 1000.0)
    prior_topic_max_age_s: float = _p(120.0, "prior_topic: estimates older than this (s, node "
                                             "clock) are stale: not used", 0.001, 86400.0)
    prior_order: str = _p("topic_first", "with prior_topic: topic_first (the robot's estimate "
                                         "while fresh, else prior_provider) or provider_first "
                                         "(prior_provider, the robot's estimate when it gives "
                                         "none)", choices=PRIOR_ORDERS)
    top_p: int = _p(50, "references retrieved before fusion with the prior", 1, 100000,
                    writable=True)
    fusion: str = _p("posterior", "posterior: visual + prior likelihood over the submaps in the "
                                  "prior's confidence region (docs/fusion.md); paper: nearest "
                                  "submap + re-rank by distance to the prior",
                     choices=FUSION_MODES, writable=True)
    use_submaps: bool = _p(True, "restrict the search to submap(s) chosen by the prior",
                           writable=True)
    rerank: bool = _p(True, "use the prior when ranking candidates (false: visual order)",
                      writable=True)
    n_submaps: int = _p(1, "paper fusion: number of submaps searched around the prior", 1,
                        100000, writable=True)
    mode: str = _p("continuous", "continuous: query the latest frame every min_period_s; "
                                 "on_trigger: only on the relocalize services", choices=MODES,
                   writable=True)
    min_period_s: float = _p(1.0, "least time between the starts of two queries (node clock: "
                                 "sim time with use_sim_time)", 0.0, 86400.0, writable=True)
    frame_id: str = _p("", "header.frame_id of the fix ('' = the image's frame_id)",
                       writable=True)
    qos: str = _p("sensor_data", "image subscription QoS: sensor_data (best effort: receives "
                                  "from best-effort and reliable cameras), best_effort, reliable; "
                                  "qos_overrides.<topic>.subscription.* override it",
                  choices=QOS_CHOICES)
    qos_depth: int = _p(5, "image subscription queue depth (1-10; the node keeps 1 frame)", 1, 10)
    subscribe_raw: bool = _p(True, "subscribe to 'image' (sensor_msgs/Image)")
    subscribe_compressed: bool = _p(False, "subscribe to 'image/compressed'")
    relocalize_wait_s: float = _p(35.0, "relocalize services: wait this long for the new fix "
                                        "(0 = answer at once that it is scheduled)", 0.0, 3600.0,
                                  writable=True)
    max_frame_age_s: float = _p(2.0, "relocalize uses the latest frame if received within "
                                     "this many seconds (node clock), else the next frame",
                                0.001, 86400.0, writable=True)
    verify_top_k: int = _p(20, "candidates verified with local features + geometry per query "
                               "(0 = off: every answer unverified, STATUS_NO_FIX)", 0, 1000,
                           writable=True)
    verify_threads: int = _p(0, "threads sharing a query's verification candidates (0 = the "
                                "usable cores, at most 4; the answers do not depend on it)",
                             0, 64)
    verify_preset: str = _p("", "verification preset this node expects ('' = the map's own); "
                               "a map of another fails configure, naming both",
                            choices=("", *PRESETS))
    verification_required: bool = _p(False, "a map without usable local features (and no "
                                            "reference_images_dir) fails configure; false: "
                                            "a warning and unverified answers")
    fix_min_p_correct: float = _p(0.99, "STATUS_FIX only when the verified answer's p_correct "
                                        "(calibrated probability of being within 25 m) is at "
                                        "least this", 0.5, 1.0, writable=True)
    fix_max_sigma_m: float = _p(50.0, "STATUS_FIX only when the fix's calibrated per-axis "
                                      "sigma is at most this (m); else STATUS_NO_FIX", 0.001,
                                MAX_SIGMA_M, writable=True)
    fix_alert_limit_m: float = _p(50.0, "STATUS_FIX only when the answer's protection level "
                                        "(m, integrity risk 1e-3) is below this alert limit",
                                  0.001, MAX_SIGMA_M, writable=True)
    trust_prior_for_fix: bool = _p(False, "an answer decisive only because the prior removed "
                                          "far look-alikes (prior_resolved) may be STATUS_FIX",
                                   writable=True)
    trust_operator_prior: bool = _p(False, "... only when the prior carries its own sigma_km "
                                           "(an operator's hint: the fixed provider)",
                                    writable=True)
    fallback_status: str = _p("no_fix", "NavSatFix status of answers failing the status rule "
                                        "(docs/verification.md): no_fix or fix",
                              choices=FALLBACK_STATUS, writable=True)
    fallback_min_sigma_m: float = _p(0.0, "least 1-sigma of an answer failing the status rule "
                                          "(m; 0 = its calibrated sigma)", 0.0, MAX_SIGMA_M,
                                     writable=True)
    altitude_m: float = _p(0.0, "altitude published in the fix (images give none)",
                           -11000.0, 100000.0, writable=True)
    altitude_sigma_m: float = _p(1000.0, "1-sigma of the published altitude (m)", 0.001,
                                 MAX_SIGMA_M, writable=True)
    fix_durability: str = _p("volatile", "QoS durability of 'fix' and 'pose' (reliable): "
                                         "transient_local keeps the last one for subscribers "
                                         "that join later; volatile keeps none",
                             choices=DURABILITY)
    pose_frame: str = _p("utm", "metric frame of the 'pose' output "
                                "(PoseWithCovarianceStamped, STATUS_FIX results only): utm, "
                                "local_enu (tangent plane at datum_lat/datum_lon) or none",
                         choices=POSE_FRAMES)
    pose_frame_id: str = _p("", "header.frame_id of the pose ('' = 'utm' or 'local_enu', the "
                                "frames of navsat_transform's broadcast_cartesian_transform)")
    pose_on: str = _p("relocalize", "which fixes also go out as a pose: relocalize (answers to "
                                    "the relocalize services: an initial pose) or every_fix",
                      choices=POSE_ON, writable=True)
    utm_zone: int = _p(0, "pose_frame utm: 0 = the zone of each fix (Norway/Svalbard "
                          "exceptions included); 1-60 = always this zone (navsat_transform "
                          "keeps the zone of its datum)", 0, 60)
    # no declared range: NaN (unset) is their default; validate() checks -90..90 / -180..180
    datum_lat: float = _p(math.nan, "pose_frame local_enu: latitude of the frame's origin "
                                    "(deg, -90..90; required for local_enu)")
    datum_lon: float = _p(math.nan, "pose_frame local_enu: longitude of the frame's origin "
                                    "(deg, -180..180; required for local_enu)")
    datum_yaw: float = _p(0.0, "pose_frame local_enu: angle of the frame's x axis from east, "
                               "counter-clockwise (rad; 0 = x east, y north)",
                          -2 * math.pi, 2 * math.pi)
    publish_debug: bool = _p(False, "publish ~/debug_image/compressed (query beside the chosen "
                                    "reference) and ~/candidates for every query",
                             writable=True)
    reference_images_dir: str = _p("", "folder of the map's reference images: verification of "
                                       "maps that store no local features, and the debug view "
                                       "('' = the map's own images/ folder, if it has one; the "
                                       "debug view also finds the folder a build-map --images "
                                       "map records, each picture checked by sha256)")
    diagnostics_period_s: float = _p(1.0, "period of /diagnostics (also sent after each fix)",
                                     0.01, 3600.0)
    hardware_id: str = _p("vlm_vpr", "DiagnosticStatus.hardware_id", writable=True)
    prior: dict = field(default_factory=dict, metadata={"doc": "prior provider settings"})
    descriptor_options: dict = field(default_factory=dict,
                                     metadata={"doc": "descriptor settings (device, weights)"})
    #: verification's learned local features / matcher (e.g. weights paths, device), as the
    #: CLI's --feature-option / --matcher-option; never stored in the map
    feature_options: dict = field(default_factory=dict, metadata={
        "doc": "local-feature settings of verification (learned features: weights, device)"})
    matcher_options: dict = field(default_factory=dict, metadata={
        "doc": "matcher settings of verification (LightGlue: weights, device)"})

    def verification_config(self) -> VerificationConfig:
        return VerificationConfig(self.verify_top_k, self.verification_required,
                                  os.path.expanduser(self.reference_images_dir),
                                  threads=self.verify_threads,
                                  feature_options=_expanded(self.feature_options),
                                  matcher_options=_expanded(self.matcher_options),
                                  preset=self.verify_preset)

    def status_policy(self) -> StatusPolicy:
        return StatusPolicy(self.fix_min_p_correct, self.fix_max_sigma_m,
                            self.trust_prior_for_fix, self.trust_operator_prior,
                            self.fallback_status, self.fallback_min_sigma_m,
                            self.fix_alert_limit_m)

    def localizer_config(self) -> LocalizerConfig:
        return LocalizerConfig(top_p=self.top_p, fusion=self.fusion,
                               use_submaps=self.use_submaps, rerank=self.rerank,
                               n_submaps=self.n_submaps)


def _expanded(options: Mapping[str, Any]) -> dict[str, Any]:
    """Options with ``~`` expanded in ``weights`` paths (as for map_dir)."""
    return {k: os.path.expanduser(v) if k == "weights" and isinstance(v, str) else v
            for k, v in options.items()}


#: scalar parameters: name → spec, in declaration order
PARAMETER_SPECS: dict[str, ParamSpec] = {
    f.name: ParamSpec(f.name, f.default, f.metadata["doc"], str(f.type),
                      f.metadata.get("range"), f.metadata.get("choices"),
                      read_only=not f.metadata.get("writable", False))
    for f in dataclasses.fields(NodeConfig) if f.name not in NESTED
}
#: parameters that may change at runtime (validated like at start-up, used from the next query)
RUNTIME_WRITABLE = frozenset(n for n, p in PARAMETER_SPECS.items() if not p.read_only)
#: scalar parameters: name → (default, description), in declaration order
PARAMETERS: dict[str, tuple[Any, str]] = {n: (p.default, p.doc)
                                          for n, p in PARAMETER_SPECS.items()}
_TYPES = {f.name: f.type for f in dataclasses.fields(NodeConfig)}
_MAP_SETTINGS = ("map_dir", "descriptor", "verify_map", "descriptor_options",
                 "feature_options", "matcher_options", "verify_preset")


def refusal_reason(name: str) -> str:
    """Why a structural parameter cannot change at runtime, and how to change it."""
    head = name.partition(".")[0]
    restart = f"restart the node with the new value (-p {name}:=... or the params file)"
    if head in _MAP_SETTINGS:
        how = ("the map and its descriptor are loaded at start (lifecycle: configure); to use "
               f"what changed inside map_dir call the map_reload service, otherwise {restart}")
    elif head in ("prior_provider", "prior") or head.startswith("prior_"):
        how = f"the prior provider is created at start (lifecycle: configure); {restart}"
    else:
        how = f"topics, QoS, frames and timers are set up at start; {restart}"
    writable = ", ".join(sorted(RUNTIME_WRITABLE))
    return (f"parameter {name!r} cannot change at runtime: {how}. Writable at runtime: "
            f"{writable}")


def _coerce(name: str, value: Any) -> Any:
    kind = _TYPES[name]
    ok = {"bool": isinstance(value, bool),
          "int": isinstance(value, int) and not isinstance(value, bool),
          "float": isinstance(value, (int, float)) and not isinstance(value, bool),
          "str": isinstance(value, str)}[kind]
    if not ok:
        raise ConfigError(f"parameter {name!r} must be {'an' if kind == 'int' else 'a'} {kind}, "
                          f"got {value!r} "
                          f"({type(value).__name__})")
    return float(value) if kind == "float" else value


def from_params(values: Mapping[str, Any], check_paths: bool = True) -> NodeConfig:
    """Validate flat ROS parameter values (``prior.x`` nested names allowed) into a config
    (``check_paths``: see :func:`validate`)."""
    flat: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {n: {} for n in NESTED}
    for key, value in values.items():
        head, _, rest = key.partition(".")
        if head in NESTED and rest:
            nested[head][rest] = value
        elif key in PARAMETERS:
            flat[key] = _coerce(key, value)
        elif key in ROS_STANDARD or key.startswith("qos_overrides."):
            continue  # declared by rclpy itself
        else:
            raise ConfigError(f"unknown parameter {key!r}; valid: {', '.join(PARAMETERS)}, "
                              + ", ".join(f"{n}.<setting>" for n in NESTED))
    cfg = NodeConfig(**flat, **nested)
    validate(cfg, check_paths)
    return cfg


def _require(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    _require(value in choices, f"parameter {name!r} is {value!r}; choices: "
                               f"{', '.join(c or repr(c) for c in choices)}")


def validate(cfg: NodeConfig, check_paths: bool = True) -> None:
    """Raise ConfigError with a clear message for the first invalid value. ``check_paths``:
    also require ``map_dir`` to be a folder (the lifecycle node checks it at configure)."""
    _require(bool(cfg.map_dir.strip()), "parameter 'map_dir' is required (a map folder built "
                                        "by `vlm-vpr build-map`)")
    if check_paths:
        _require(os.path.isdir(os.path.expanduser(cfg.map_dir)),
                 f"parameter 'map_dir': {cfg.map_dir!r} is not a folder")
        _require(not cfg.reference_images_dir or os.path.isdir(os.path.expanduser(
            cfg.reference_images_dir)), f"parameter 'reference_images_dir': "
            f"{cfg.reference_images_dir!r} is not a folder")
    _choice("mode", cfg.mode, MODES)
    _choice("qos", cfg.qos, QOS_CHOICES)
    _choice("fallback_status", cfg.fallback_status, FALLBACK_STATUS)
    for name in ("prior_timeout_s", "max_frame_age_s", "diagnostics_period_s",
                 "altitude_sigma_m"):
        v = getattr(cfg, name)
        _require(math.isfinite(v) and v > 0, f"parameter {name!r} must be > 0, got {v}")
    for name in ("min_period_s", "relocalize_wait_s", "fallback_min_sigma_m"):
        v = getattr(cfg, name)
        _require(math.isfinite(v) and v >= 0, f"parameter {name!r} must be >= 0, got {v}")
    _require(math.isfinite(cfg.altitude_m), "parameter 'altitude_m' must be finite")
    _require(1 <= cfg.qos_depth <= 10, f"parameter 'qos_depth' must be in 1..10, "
                                       f"got {cfg.qos_depth}")
    _require(cfg.prior_topic_type not in ("pose", "odometry") or not cfg.prior_topic
             or cfg.pose_frame != "none", "prior_topic_type pose/odometry needs pose_frame "
             "utm or local_enu (the frame its positions are in)")
    _require(cfg.subscribe_raw or cfg.subscribe_compressed,
             "subscribe_raw and subscribe_compressed are both false: nothing to localize")
    for name, bound in (("datum_lat", 90.0), ("datum_lon", 180.0)):
        v = getattr(cfg, name)
        _require(math.isnan(v) or -bound <= v <= bound,
                 f"parameter {name!r} must be in [{-bound:g}, {bound:g}], got {v}")
        _require(cfg.pose_frame != "local_enu" or math.isfinite(v),
                 f"pose_frame 'local_enu' needs the parameter {name!r} (the frame's origin)")
    cfg.localizer_config()  # raises ConfigError on top_p/n_submaps < 1, unknown fusion
    for spec in PARAMETER_SPECS.values():  # the declared ranges (after the specific checks)
        v = getattr(cfg, spec.name)
        if spec.range is not None:
            lo, hi = spec.range
            _require(lo <= v <= hi, f"parameter {spec.name!r} must be in [{lo:g}, {hi:g}], "
                                    f"got {v}")
        if spec.choices is not None:
            _choice(spec.name, v, spec.choices)

    choose(cfg.prior_provider, available_prior_providers(), "prior provider")


# -- what the command line asked for -------------------------------------------------------------
def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    else:
        out[prefix] = value


def _applies(key: str, node_name: str, fqn: str) -> bool:
    key = str(key)
    if key.strip("/") in ("**", "*"):
        return True
    pattern = key.lstrip("/").replace("**", "*")
    return key.strip("/") == node_name or fnmatch.fnmatchcase(fqn.lstrip("/"), pattern)


def requested_parameters(argv: list[str] | None, node_name: str,
                         namespace: str = "/") -> dict[str, Any]:
    """Parameter values the user gave on the command line, in rcl's order of precedence.

    ``--params-file FILE`` and ``-p name:=value`` (or ``--param``) inside ``--ros-args``, later
    ones winning, values parsed as YAML like rcl does. rcl itself silently keeps an earlier
    value when a later one has another type (``-p top_p:=abc`` after a params file with
    ``top_p: 50`` starts with 50); comparing this with what rclpy got lets the node refuse that.
    Raises :class:`ConfigError` for a missing or malformed params file.
    """
    import yaml

    args = list(argv or [])
    fqn = f"{namespace.rstrip('/')}/{node_name}"
    for i, a in enumerate(args):  # -r __ns:=/x and -r __node:=y change what matches
        if a in ("-r", "--remap") and i + 1 < len(args):
            src, _, dst = args[i + 1].partition(":=")
            if src == "__ns":
                fqn = f"{dst.rstrip('/')}/{fqn.rsplit('/', 1)[1]}"
            elif src == "__node":
                node_name, fqn = dst, f"{fqn.rsplit('/', 1)[0]}/{dst}"
    out: dict[str, Any] = {}
    in_ros, i = False, 0
    while i < len(args):
        a = args[i]
        if a == "--ros-args":
            in_ros = True
        elif a == "--":
            in_ros = False
        elif in_ros and a in ("-p", "--param", "--params-file") and i + 1 < len(args):
            arg = args[i + 1]
            i += 1
            if a == "--params-file":
                try:
                    with open(arg, encoding="utf-8") as fh:
                        doc = yaml.safe_load(fh) or {}
                except OSError as exc:
                    raise ConfigError(f"params file {arg}: {exc.strerror}") from None
                except yaml.YAMLError as exc:
                    raise ConfigError(f"params file {arg}: invalid YAML: "
                                      f"{str(exc).splitlines()[0]}") from None
                if not isinstance(doc, dict):
                    raise ConfigError(f"params file {arg}: expected a mapping of node names")
                for key, body in doc.items():
                    if isinstance(body, dict) and _applies(key, node_name, fqn):
                        _flatten("", body.get("ros__parameters") or {}, out)
                continue
            name, sep, text = arg.partition(":=")
            if not sep:
                raise ConfigError(f"-p {arg}: expected name:=value")
            if ":" in name:  # node-specific form: node_name:param:=value
                target, _, name = name.rpartition(":")
                if not _applies(target, node_name, fqn):
                    i += 1
                    continue
            try:
                out[name] = yaml.safe_load(text) if text != "" else ""
            except yaml.YAMLError:
                out[name] = text
        i += 1
    return out


def type_conflicts(requested: Mapping[str, Any], received: Mapping[str, Any]) -> list[str]:
    """Names whose requested value has another type than the value rclpy holds (rcl kept an
    earlier value of the other type), e.g. a ``-p`` string next to a params-file number."""
    def kind(v: Any) -> str:
        if isinstance(v, bool):
            return "bool"
        if isinstance(v, (int, float)):
            return "number"
        return type(v).__name__
    return [f"parameter {k!r} is {requested[k]!r} ({kind(requested[k])}) on the command line "
            f"but {received[k]!r} ({kind(received[k])}) in an earlier params file or -p"
            for k in requested if k in received and kind(requested[k]) != kind(received[k])]

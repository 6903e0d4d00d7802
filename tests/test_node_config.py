"""Node parameter schema and validation (pure), the shipped params YAML and launch files."""

from __future__ import annotations

import ast
import os
import subprocess
from pathlib import Path

import pytest
import yaml

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.runtime.params import (NESTED, NodeConfig, PARAMETER_SPECS, PARAMETERS,
                                        RUNTIME_WRITABLE, from_params)

LAUNCH = Path(__file__).resolve().parents[1] / "launch_scripts"


def test_defaults_and_nested_settings(tmp_path):
    cfg = from_params({"map_dir": str(tmp_path), "prior_provider": "fixed", "prior.lat": 1.5,
                       "prior.lon": 2, "descriptor_options.device": "cpu", "min_period_s": 2,
                       "use_sim_time": False, "start_type_description_service": True,
                       "qos_overrides./parameter_events.publisher.depth": 1000})
    assert cfg.prior == {"lat": 1.5, "lon": 2} and cfg.descriptor_options == {"device": "cpu"}
    assert cfg.min_period_s == 2.0 and isinstance(cfg.min_period_s, float)
    assert cfg.mode == "continuous" and cfg.qos == "sensor_data"
    assert cfg.fallback_status == "no_fix"
    lc = cfg.localizer_config()
    assert (lc.top_p, lc.use_submaps, lc.rerank, lc.n_submaps) == (50, True, True, 1)
    assert set(PARAMETERS) == {f for f in NodeConfig.__dataclass_fields__} - set(NESTED)


def test_learned_feature_weights_reach_verification(tmp_path):
    """feature_options.* / matcher_options.* are passed to the verification stage (as the CLI's
    --feature-option / --matcher-option), weights paths with ~ expanded."""
    cfg = from_params({"map_dir": str(tmp_path), "feature_options.weights": "~/w/disk.pth",
                       "matcher_options.weights": "/w/lg.pth", "matcher_options.device": "cpu"})
    v = cfg.verification_config()
    assert v.feature_options == {"weights": os.path.expanduser("~/w/disk.pth")}
    assert v.matcher_options == {"weights": "/w/lg.pth", "device": "cpu"}
    assert NodeConfig().verification_config().feature_options == {}


def test_verify_preset_reaches_verification(tmp_path):
    """verify_preset (as the CLI's --verify-preset): the verification stage refuses a map of
    another preset, naming both (tests/test_verify_preset.py)."""
    cfg = from_params({"map_dir": str(tmp_path), "verify_preset": "xfeat_lighterglue"})
    assert cfg.verification_config().preset == "xfeat_lighterglue"
    assert NodeConfig().verification_config().preset == ""


def test_docs_parameter_table_is_the_schema():
    """docs/node.md's parameter table lists every parameter once, and its runtime column says
    exactly which ones are writable at runtime (the runtime-tuning contract)."""
    import re

    text = (Path(__file__).resolve().parents[1] / "docs" / "node.md").read_text()
    rows = re.findall(r"^\| `([a-z_0-9]+)` \| (?:bool|int|float|str) \|[^|]*\|[^|]*\| (yes)? ?\|",
                      text, re.M)
    assert [n for n, _ in rows] == list(PARAMETER_SPECS)
    assert {n for n, w in rows if w} == RUNTIME_WRITABLE
    for name in ("verify_top_k", "fix_min_p_correct", "fix_max_sigma_m", "trust_prior_for_fix",
                 "trust_operator_prior", "fallback_status", "publish_debug"):
        assert name in RUNTIME_WRITABLE, name
    assert all(doc for _, doc in PARAMETERS.values())


@pytest.mark.parametrize("values,match", [
    ({"top_pp": 3}, "unknown parameter 'top_pp'; valid: map_dir, descriptor"),
    ({"top_p": "50"}, "'top_p' must be an int, got '50'"),
    ({"use_submaps": 1}, "'use_submaps' must be a bool"),
    ({"min_period_s": "fast"}, "'min_period_s' must be a float"),
    ({"mode": "sometimes"}, "'mode' is 'sometimes'; choices: continuous, on_trigger"),
    ({"qos": "fast"}, "choices: sensor_data, best_effort, reliable"),
    ({"fallback_status": "maybe"}, "choices: no_fix, fix"),
    ({"prior_timeout_s": 0.0}, "'prior_timeout_s' must be > 0"),
    ({"min_period_s": -1.0}, "'min_period_s' must be >= 0"),
    ({"altitude_m": float("nan")}, "'altitude_m' must be finite"),
    ({"qos_depth": 0}, "'qos_depth' must be in 1..10"),
    ({"top_p": 0}, "top_p"),
    ({"subscribe_raw": False}, "nothing to localize"),
    ({"prior_provider": "oracle"}, "unknown prior provider 'oracle'; choices: .*fixed"),
    ({"verify_preset": "orb"}, "'verify_preset' is 'orb'; choices: '', sift, xfeat_lighterglue"),
    ({"map_dir": ""}, "'map_dir' is required"),
    ({"map_dir": "/nonexistent/map"}, "is not a folder"),
])
def test_invalid_values_are_rejected(tmp_path, values, match):
    with pytest.raises(ConfigError, match=match):
        from_params({"map_dir": str(tmp_path), **values})


def test_params_yaml_is_valid_and_documents_every_parameter(tmp_path):
    text = (LAUNCH / "vlm_vpr_params.yaml").read_text()
    params = yaml.safe_load(text)["/**"]["ros__parameters"]
    assert set(params) == set(PARAMETERS)  # every parameter is in the documented file
    for name, value in params.items():
        default = PARAMETERS[name][0]
        if name != "map_dir" and not (value != value and default != default):  # NaN == NaN
            assert value == default, f"{name}: YAML and schema defaults differ"
    cfg = from_params({**params, "map_dir": str(tmp_path)})
    assert cfg.map_dir == str(tmp_path)
    for name in PARAMETERS:
        assert f"\n    {name}:" in text


def test_launch_file_is_valid_python_naming_the_console_script():
    src = (LAUNCH / "vlm_vpr.launch.py").read_text()
    tree = ast.parse(src)  # launch/launch_ros are not on PyPI: syntax and content only
    funcs = [n.name for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert "generate_launch_description" in funcs
    assert '"vlm_vpr_node"' in src and "vlm_vpr_params.yaml" in src
    assert '"vlm_vpr_lifecycle_node"' in src and "LifecycleNode" in src
    declared = {n.args[0].value for n in ast.walk(tree) if isinstance(n, ast.Call)
                and getattr(n.func, "id", "") == "DeclareLaunchArgument"}
    assert {"map_dir", "params_file", "image", "namespace", "use_sim_time", "qos",
            "prior_provider", "lifecycle", "autostart", "fastdds_profile", "pose",
            "fix_durability", "publish_debug"} <= declared
    assert '[share, "launch",' in src and '"vlm_vpr_params.yaml"]' in src  # installed
    setup = (LAUNCH.parent / "setup.py").read_text()
    assert "vlm_vpr_node = vlm_vpr_ros.ros.node:main" in setup
    assert "vlm_vpr_lifecycle_node = vlm_vpr_ros.ros.node:lifecycle_main" in setup


def test_run_node_script_rejects_bad_parameters_clearly(tmp_path):
    """run_node.sh starts the real node; an invalid value stops it with exit 2 and a FATAL line."""
    script = LAUNCH / "run_node.sh"
    assert os.access(script, os.X_OK)
    env = {**os.environ, "ROS_DOMAIN_ID": "97", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    proc = subprocess.run([str(script), "-p", f"map_dir:={tmp_path}", "-p", "mode:=sometimes"],
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 2
    assert "invalid configuration" in proc.stderr and "choices: continuous, on_trigger" in \
        proc.stderr
    missing = subprocess.run([str(script), str(tmp_path / "nope.yaml")], capture_output=True,
                             text=True, timeout=30, env=env)
    assert missing.returncode == 2 and "params file not found" in missing.stderr

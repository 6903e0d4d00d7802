"""Checkpoint handling of the deep VPR models through the public paths: ``weights=PATH``, the
torch hub cache (``TORCH_HOME``), ``vlm-vpr weights``, clear errors for missing / wrong-shaped /
unsafe files, and map manifests that refuse a different descriptor."""

from __future__ import annotations

import csv
import json
import pickle
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from vlm_vpr_ros.descriptors import create_descriptor  # noqa: E402
from vlm_vpr_ros.descriptors.deep.specs import get_spec  # noqa: E402
from vlm_vpr_ros.descriptors.deep.torch_descriptor import DeepDescriptor  # noqa: E402
from vlm_vpr_ros.descriptors.deep.weights import (build_model, file_sha256, recipe_state_dict,
                                                  save_state_dict)
from vlm_vpr_ros.errors import DescriptorError, MapError  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402

VLM_VPR = [sys.executable, "-m", "vlm_vpr_ros.cli"]
MIX = get_spec("mixvpr")  # the smallest model (10 M parameters, 40 MB checkpoint)


def run_cli(*args, env=None, check=True):
    proc = subprocess.run([*VLM_VPR, *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.fixture(scope="module")
def recipe():
    return recipe_state_dict(build_model(MIX))


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory, recipe):
    """A checkpoint file saved from the model (plain state_dict, as the official release)."""
    return save_state_dict(recipe, tmp_path_factory.mktemp("w") / MIX.release)


@pytest.fixture(scope="module")
def images(demo_data):
    return [load_image(p) for p in sorted((demo_data / "images").iterdir())[:3]]


@pytest.fixture(scope="module")
def reference(recipe, images):
    return DeepDescriptor(MIX, {"device": "cpu"}, state_dict=recipe).describe(images)


@pytest.fixture
def hub(tmp_path, monkeypatch):
    """An empty torch hub cache selected with TORCH_HOME (as a user would)."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    return tmp_path / "torch" / "hub" / "checkpoints"


def test_roundtrip_from_path(ckpt, images, reference):
    desc = create_descriptor("mixvpr", {"weights": str(ckpt), "device": "cpu"})
    np.testing.assert_array_equal(desc.describe(images), reference)
    ident = desc.identity()
    assert ident["release"] == MIX.release and ident["dim"] == 512
    assert ident["weights_sha256"] == file_sha256(ckpt)
    assert str(ckpt) not in json.dumps(ident) and "cpu" not in json.dumps(ident)
    assert ident["preprocessing"]["resize"] == [320, 320]


def test_roundtrip_from_hub_cache(hub, ckpt, images, reference):
    with pytest.raises(DescriptorError) as err:
        create_descriptor("mixvpr", {"device": "cpu"})
    msg = str(err.value)
    for part in (MIX.release, str(hub), "vlm-vpr weights fetch mixvpr", MIX.human_url):
        assert part in msg
    hub.mkdir(parents=True)
    (hub / MIX.release).write_bytes(ckpt.read_bytes())
    desc = create_descriptor("mixvpr", {"device": "cpu"})
    np.testing.assert_array_equal(desc.describe(images), reference)


def test_lightning_wrapped_checkpoint(tmp_path, recipe, images, reference):
    path = tmp_path / "wrapped.ckpt"
    torch.save({"state_dict": recipe, "epoch": 3}, path)
    desc = create_descriptor("mixvpr", {"weights": str(path), "device": "cpu"})
    np.testing.assert_array_equal(desc.describe(images), reference)


def test_wrong_checkpoints_are_clear_errors(tmp_path, recipe):
    wrong = save_state_dict(recipe_state_dict(build_model(get_spec("mixvpr_4096"))),
                            tmp_path / "4096.ckpt")
    with pytest.raises(DescriptorError, match="wrong shape") as err:
        create_descriptor("mixvpr", {"weights": str(wrong), "device": "cpu"})
    assert "aggregator.channel_proj.weight (1024, 1024) != (256, 1024)" in str(err.value)
    partial = {k: v for k, v in recipe.items() if k != "aggregator.row_proj.bias"}
    partial["extra.weight"] = torch.zeros(2)
    save_state_dict(partial, tmp_path / "partial.ckpt")
    with pytest.raises(DescriptorError) as err:
        create_descriptor("mixvpr", {"weights": str(tmp_path / "partial.ckpt")})
    assert "missing: aggregator.row_proj.bias" in str(err.value)
    assert "unexpected: extra.weight" in str(err.value)
    (tmp_path / "page.html").write_text("<html>Google Drive - virus scan warning</html>")
    with pytest.raises(DescriptorError, match="not a loadable torch checkpoint"):
        create_descriptor("mixvpr", {"weights": str(tmp_path / "page.html")})
    with open(tmp_path / "evil.pth", "wb") as fh:  # arbitrary objects are refused
        pickle.dump({"x": Fraction(1, 3)}, fh, protocol=2)
    with pytest.raises(DescriptorError, match="weights_only=True"):
        create_descriptor("mixvpr", {"weights": str(tmp_path / "evil.pth")})
    torch.save([1, 2, 3], tmp_path / "list.pth")
    with pytest.raises(DescriptorError, match="state_dict"):
        create_descriptor("mixvpr", {"weights": str(tmp_path / "list.pth")})


def test_cli_fetch_list_check(hub, ckpt, tmp_path):
    """``weights fetch --url`` (file:// stands in for the release URL) validates the file and
    stores it where the loader looks; a file that does not fit is not stored."""
    import os

    env = dict(os.environ)
    out = json.loads(run_cli("weights", "list", "--json", env=env).stdout)
    row = {r["model"]: r for r in out["models"]}["mixvpr"]
    assert row["present"] is False and row["path"] == str(hub / MIX.release)
    assert run_cli("weights", "path", "boq", env=env).stdout.strip() == str(
        hub / "resnet50_16384.pth")
    bad = save_state_dict({"x": torch.zeros(1)}, tmp_path / "bad.ckpt")
    proc = run_cli("weights", "fetch", "mixvpr", "--url", bad.as_uri(), env=env, check=False)
    assert proc.returncode == 2 and "does not fit" in proc.stderr
    assert not hub.exists() or not any(hub.iterdir())  # nothing half-written is left
    run_cli("weights", "fetch", "mixvpr", "--url", ckpt.as_uri(), env=env)
    assert file_sha256(hub / MIX.release) == file_sha256(ckpt)
    res = json.loads(run_cli("weights", "check", "mixvpr", "--json", env=env).stdout)
    assert res["ok"] and res["sha256"] == file_sha256(ckpt)
    out = json.loads(run_cli("weights", "list", "--json", env=env).stdout)
    assert {r["model"]: r for r in out["models"]}["mixvpr"]["present"] is True
    proc = run_cli("weights", "fetch", "nope", env=env, check=False)
    assert proc.returncode == 2 and "choices: boq, cosplace" in proc.stderr


def test_map_records_and_enforces_descriptor(tmp_path, demo_data, ckpt, caplog):
    """A map built with a deep descriptor stores model/release/preprocessing (no paths) and a
    pipeline with another descriptor refuses it."""
    from vlm_vpr_ros.mapping.build_images import build_map
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:4]
    coords = tmp_path / "coords.csv"
    with open(coords, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["file", "lat", "lon"], extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    out = tmp_path / "map"
    build_map(demo_data / "images", coords, out, descriptor="mixvpr",
              descriptor_config={"weights": str(ckpt), "device": "cpu"}, partition="kmeans",
              clusters=2, progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    ident = manifest["descriptor"]
    assert (ident["name"], ident["dim"], ident["release"]) == ("mixvpr", 512, MIX.release)
    assert ident["preprocessing"]["interpolation"] == "bicubic"
    assert str(ckpt) not in json.dumps(manifest)
    pipe = LocalizationPipeline.open(out, descriptor_config={"weights": str(ckpt)})
    hyp = pipe.localize_image(load_image(demo_data / "images" / rows[1]["file"]), None)
    assert (hyp.lat, hyp.lon) == pytest.approx((float(rows[1]["lat"]), float(rows[1]["lon"])))
    with pytest.raises(MapError, match="mixvpr"):
        LocalizationPipeline.open(out, descriptor="cosplace")
    assert ident["weights_sha256"] and "another checkpoint" not in caplog.text
    ident["weights_sha256"] = "0" * 64  # built with another checkpoint: loads, with a warning
    (out / "manifest.json").write_text(json.dumps(manifest))
    LocalizationPipeline.open(out, descriptor_config={"weights": str(ckpt)}, verify=False)
    assert "another checkpoint of mixvpr" in caplog.text
    ident["preprocessing"]["resize"] = [384, 384]  # a map from other preprocessing is refused
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MapError, match="preprocessing"):
        LocalizationPipeline.open(out, descriptor_config={"weights": str(ckpt)}, verify=False)


@pytest.mark.parametrize("config, message", [
    ({"weight": "x"}, r"unknown .* option\(s\) \['weight'\]; valid options"),
    ({"device": "tpu"}, "choices: auto, cpu, cuda"),
    ({"batch_size": 0}, "batch_size must be 1..1024"),
    ({"fp16": "yes"}, "fp16 must be true or false"),
    ({"weights": 5}, "weights must be a file path"),
    ({"resize": [10, "a"]}, r"resize must be \[H, W\]"),
])
def test_config_errors(config, message):
    from vlm_vpr_ros.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        create_descriptor("cosplace", config)
    with pytest.raises(ConfigError, match="fixed at"):
        create_descriptor("boq", {"resize": [480, 640]})
    if not torch.cuda.is_available():
        with pytest.raises(DescriptorError, match="CUDA is not available"):
            create_descriptor("mixvpr", {"device": "cuda"})


def test_garbage_bytes_are_always_a_descriptor_error(tmp_path):
    """Random bytes reach many corners of torch's unpickler (IndexError, struct.error, ...):
    every one must be a DescriptorError naming the file, never an internal error. 300 fixed
    seeds, plus bytes that look like a legacy pickle stream."""
    from vlm_vpr_ros.descriptors.deep.weights import read_state_dict

    rng = np.random.default_rng(11)
    for i in range(300):
        data = rng.integers(0, 256, int(rng.integers(1, 4096)), dtype=np.uint8).tobytes()
        if i % 3 == 0:
            data = b"\x80\x02" + data  # pickle protocol 2 header: the legacy loader path
        w = tmp_path / f"w{i}.pth"
        w.write_bytes(data)
        with pytest.raises(DescriptorError, match=str(w)):
            read_state_dict(w)

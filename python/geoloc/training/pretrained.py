"""Starting weights for the descriptor network (``geoloc train --init FILE``).

Two layouts are accepted, both read with ``torch.load(weights_only=True)`` (a file that
would run code under a plain pickle load is refused, never executed):

* **geoloc's own** — a checkpoint written by ``geoloc train --checkpoint`` or a bare
  ``state_dict`` of :class:`~geoloc.training.network.DescriptorNet`: loaded as it is, every
  tensor, or refused when it does not fit the network (backbone, ``dim``).
* **torchvision's GoogLeNet** — the ``state_dict`` of ``torchvision.models.googlenet`` (the
  layout of ImageNet or Places weights converted to torch; ``module.`` prefixes of a
  ``DataParallel`` save are stripped). It is mapped onto geoloc's GoogLeNet, whose blocks are
  the same Inception v1 with the same batch-normalized convolutions:

  - ``conv1``/``conv2``/``conv3`` → the stem's three convolutions; the first convolution's
    RGB filters are summed into one grayscale channel: for a gray image g replicated into
    (g, g, g), Σ_c W_c ∗ g = (Σ_c W_c) ∗ g, so the mapped network sees a gray image as the
    original saw its grey RGB version (the input normalisation may differ);
  - ``inceptionXY.branch1`` / ``branch2`` / ``branch3`` / ``branch4.1`` → the block's 1×1,
    1×1→3×3, 1×1→"5×5" and pool-projection branches. torchvision's third branch is 3×3
    where the paper's is 5×5; the 3×3 kernel is zero-padded to 5×5, which with padding 2
    gives exactly the 3×3 convolution with padding 1;
  - the classifier heads (``fc``, ``aux1``, ``aux2``) are dropped; geoloc's descriptor head
    (``fc``: 1024 → dim) keeps its fresh initialization.

:func:`init_weights` loads a file into a network and returns an :class:`InitReport` of what
was loaded, adapted, dropped and left as initialized.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .._io import special_kind
from ..exceptions import InvalidInputError
from .network import INCEPTION_LAYOUT, POOL_AFTER, DescriptorNet

#: The ``format`` field of a checkpoint written by ``geoloc train --checkpoint``.
CHECKPOINT_FORMAT = "geoloc-descriptor-checkpoint"
#: torchvision's stem convolutions → geoloc's (``backbone.stem.<i>``).
STEM = {"conv1": 0, "conv2": 2, "conv3": 3}
#: torchvision's branch prefixes inside an inception block → geoloc's.
BRANCHES = {
    "branch1": "branch1",
    "branch2.0": "branch3.0",
    "branch2.1": "branch3.1",
    "branch3.0": "branch5.0",
    "branch3.1": "branch5.1",
    "branch4.1": "branch_pool.1",
}
#: torchvision's classifier heads: dropped.
HEADS = ("fc.", "aux1.", "aux2.")
#: A conv-BN unit: ``.conv.weight`` → ``.0.weight``, ``.bn.<x>`` → ``.1.<x>``.
_UNIT = re.compile(r"^(?P<unit>.+)\.(?P<part>conv|bn)\.(?P<tensor>\w+)$")
_INCEPTION = re.compile(r"^inception(?P<block>\d[a-e])\.(?P<branch>branch\d(?:\.\d)?)$")


def _block_indices() -> dict[str, int]:
    """Inception block name ("3a") → its index in ``GoogLeNet.blocks`` (pools included)."""
    out, i = {}, 0
    for name, *_ in INCEPTION_LAYOUT:
        out[name] = i
        i += 2 if name in POOL_AFTER else 1
    return out


BLOCKS = _block_indices()


@dataclass(frozen=True)
class InitReport:
    """What :func:`init_weights` did: the file's ``layout``; geoloc's tensors ``loaded``
    from it; those ``adapted`` on the way (name, how); the file's tensors ``dropped``; and
    geoloc's tensors ``not_loaded`` (left as initialized)."""

    layout: str
    loaded: tuple[str, ...]
    adapted: tuple[tuple[str, str], ...]
    dropped: tuple[str, ...]
    not_loaded: tuple[str, ...]

    def summary(self) -> str:
        """One paragraph for the command line."""
        lines = [f"--init: {self.layout} weights, {len(self.loaded)} tensors loaded"]
        for name, how in self.adapted:
            lines.append(f"  adapted {name}: {how}")
        if self.dropped:
            lines.append(f"  dropped from the file ({len(self.dropped)}): {_short(self.dropped)}")
        if self.not_loaded:
            lines.append(f"  left as initialized ({len(self.not_loaded)}): {_short(self.not_loaded)}")
        return "\n".join(lines)


def _short(names: tuple[str, ...], n: int = 6) -> str:
    return ", ".join(names[:n]) + (f", … ({len(names) - n} more)" if len(names) > n else "")


def torchvision_name(name: str) -> str | None:
    """geoloc's parameter name for a torchvision GoogLeNet one; None for a classifier head
    or a name that is not part of the Inception v1 feature extractor."""
    m = _UNIT.match(name)
    if m is None or name.startswith(HEADS):
        return None
    unit, part, tensor = m["unit"], m["part"], m["tensor"]
    index = "0" if part == "conv" else "1"
    if unit in STEM:
        return f"backbone.stem.{STEM[unit]}.{index}.{tensor}"
    b = _INCEPTION.match(unit)
    if b is None or b["block"] not in BLOCKS or b["branch"] not in BRANCHES:
        return None
    return f"backbone.blocks.{BLOCKS[b['block']]}.{BRANCHES[b['branch']]}.{index}.{tensor}"


def is_torchvision_googlenet(state: dict[str, torch.Tensor]) -> bool:
    """Whether a state dict has torchvision's GoogLeNet layout."""
    return "conv1.conv.weight" in state and "inception3a.branch1.conv.weight" in state


def _adapt(name: str, value: torch.Tensor, want: torch.Size) -> tuple[torch.Tensor, str | None]:
    """``value`` shaped as ``want``: RGB filters summed to one channel, a 3×3 kernel
    zero-padded to 5×5; unchanged when the shapes agree (None: no adaptation)."""
    if value.shape == want:
        return value, None
    if value.dim() == 4 and want[1] == 1 and value.shape[1] == 3 and value.shape[2:] == want[2:] and value.shape[0] == want[0]:
        return value.sum(dim=1, keepdim=True), "RGB filters summed into one grayscale channel"
    if value.dim() == 4 and value.shape[:2] == want[:2] and tuple(value.shape[2:]) == (3, 3) and tuple(want[2:]) == (5, 5):
        return torch.nn.functional.pad(value, (1, 1, 1, 1)), "3×3 kernel zero-padded to 5×5 (the same convolution)"
    raise InvalidInputError(f"init_from: tensor {name!r} has shape {tuple(value.shape)}, the network's is {tuple(want)}")


def _from_torchvision(model: DescriptorNet, state: dict[str, torch.Tensor], source: str) -> InitReport:
    if model.backbone_name != "googlenet":
        raise InvalidInputError(f"init_from: {source!r} holds torchvision GoogLeNet weights; they need the googlenet backbone (not --tiny)")
    own = model.state_dict()
    mapped: dict[str, torch.Tensor] = {}
    adapted: list[tuple[str, str]] = []
    dropped: list[str] = []
    for name, value in state.items():
        target = torchvision_name(name)
        if target is None or target not in own:
            dropped.append(name)
            continue
        mapped[target], how = _adapt(name, value, own[target].shape)
        if how is not None:
            adapted.append((target, how))
    missing = [k for k in own if k.startswith("backbone.") and k not in mapped]
    if missing:
        raise InvalidInputError(
            f"init_from: {source!r} is an incomplete torchvision GoogLeNet: no weights for {_short(tuple(missing))}"
        )
    model.load_state_dict(mapped, strict=False)
    not_loaded = tuple(k for k in own if k not in mapped)
    return InitReport("torchvision GoogLeNet", tuple(mapped), tuple(adapted), tuple(dropped), not_loaded)


def load_checkpoint(path: str | os.PathLike[str], name: str = "checkpoint") -> dict[str, Any]:
    """A checkpoint written by :func:`train` (or a bare state_dict, as ``{"model": …}``);
    loaded with ``weights_only=True`` (never runs code from the file). Refusals name the
    argument ``name`` that gave ``path``."""
    p = Path(path)
    kind = special_kind(p)
    if kind is not None:  # never opened: torch.load would block on a FIFO
        raise InvalidInputError(f"{name}: {str(p)!r} is {kind}, not a regular file")
    try:
        data = torch.load(p, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise InvalidInputError(f"{name}: no file {str(p)!r}") from None
    except Exception as e:  # torch raises assorted errors for foreign or truncated files
        raise InvalidInputError(f"{name}: {str(p)!r} is not a readable torch checkpoint ({type(e).__name__})") from None
    if not isinstance(data, dict):
        raise InvalidInputError(f"{name}: {str(p)!r} holds a {type(data).__name__}, not a checkpoint or state_dict")
    if data.get("format") == CHECKPOINT_FORMAT:
        return data
    if all(isinstance(v, torch.Tensor) for v in data.values()):
        return {"model": data}
    raise InvalidInputError(f"{name}: {str(p)!r} is neither a geoloc checkpoint nor a state_dict")


def load_weights(model: DescriptorNet, state: dict[str, torch.Tensor], source: str) -> None:
    """Loads geoloc's own ``state`` into ``model``, every tensor, or refuses it by name."""
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = str(e).strip().splitlines()[0]
        raise InvalidInputError(
            f"init_from: the weights in {source!r} do not fit a {model.backbone_name} network with dim {model.dim} ({first})"
        ) from None


def init_weights(
    model: DescriptorNet, path: str | os.PathLike[str], state: dict[str, torch.Tensor] | None = None
) -> InitReport:
    """Loads the weights in ``path`` (geoloc's checkpoint or state dict, or torchvision's
    GoogLeNet state dict: see the module doc) into ``model``; what was loaded. ``state``: the
    file's weights as :func:`load_checkpoint` already read them (``["model"]``), so that one
    read serves a check and the training (``path`` then only names them).

    Raises :class:`~geoloc.InvalidInputError` for a file that is not a safe torch checkpoint,
    or whose weights do not fit ``model``."""
    if state is None:
        state = load_checkpoint(path, "init_from")["model"]
    state = {k.removeprefix("module."): v for k, v in state.items()}
    source = str(Path(path))
    if is_torchvision_googlenet(state):
        return _from_torchvision(model, state, source)
    load_weights(model, state, source)
    return InitReport("geoloc", tuple(state), (), (), ())

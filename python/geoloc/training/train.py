"""Siamese training of the descriptor network (the paper's schedule by default).

Each epoch draws ``n_pos`` positive and ``n_neg`` negative pairs from the poses
(:mod:`.pairs`), runs both images of every pair through the *same* network (shared weights:
the two twins are one module) in mini-batches of ``batch_size`` pairs, and takes an Adam step
on the contrastive loss (:mod:`.loss`) per mini-batch. Paper defaults: Adam, lr 1e-3, batch
128, 128 + 128 pairs per epoch, 500 epochs, margin 1.

Reproducible: the network's initial weights come from ``seed``; every epoch re-seeds torch
and draws its pairs from a generator seeded by (seed, epoch), so a run resumed from a
checkpoint continues exactly as the uninterrupted run would have (bit-identical on the CPU);
``torch.use_deterministic_algorithms`` is on during training. Checkpoints are written
atomically every ``checkpoint_every`` epochs and at the end; ``init_from`` starts from the
weights of a local checkpoint file (nothing is ever downloaded). CUDA is used when present
(``device="auto"``).

A validation block — the last ``validation`` fraction of the frames, ``validation_margin``
frames before it left out too — is held out of training; recall@1 on it every
``eval_every`` epochs picks the epoch whose network is returned (:mod:`.selection`).

Images are read once through ``geoloc.descriptor.to_gray`` (uint8, 224×224, 50 kB each) and
normalized per mini-batch by ``geoloc.descriptor.normalize``: the same preprocessing that
:class:`geoloc.descriptor.OnnxDescriptor` applies at run time.
"""

from __future__ import annotations

import io
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np
import torch
from numpy.typing import NDArray

from .._io import write_bytes_atomic
from .._validation import real_scalar
from ..descriptor import normalize
from ..exceptions import InvalidInputError
from .evaluate import MEASUREMENTS, VALIDATION_FRACTION, VALIDATION_MARGIN
from .frames import PosedFrames, gray_images, poses_of
from .loss import DEFAULT_MARGIN, contrastive_loss
from .network import BACKBONES, DEFAULT_DIM, DescriptorNet, build_network
from .pairs import PairSampler, PairThresholds
from .pretrained import CHECKPOINT_FORMAT, init_weights, load_checkpoint, load_weights
from .selection import Selector, split_validation

__all__ = ["CHECKPOINT_FORMAT", "TrainConfig", "TrainResult", "embed", "load_checkpoint", "load_network", "train"]

CHECKPOINT_VERSION = 1
#: Images per forward pass when computing descriptors without gradients.
EMBED_BATCH = 64
#: ``augment``: each training image x (normalized) becomes g·x + b, log g ~ U(±AUGMENT_LOG_GAIN),
#: b ~ U(±AUGMENT_OFFSET) — exposure and contrast changes a camera makes on its own.
AUGMENT_LOG_GAIN = 0.3
AUGMENT_OFFSET = 0.4


#: The largest learning rate accepted: Adam and AdamW move every weight by about lr per step,
#: and the networks' weights are of order 0.1, so a larger rate only diverges.
MAX_LR = 1.0
#: torch.manual_seed takes a signed 64-bit seed.
MAX_SEED = 2**63 - 1


@dataclass(frozen=True)
class TrainConfig:
    """Training options; the defaults are the paper's schedule (see the module doc)."""

    backbone: str = "googlenet"
    dim: int = DEFAULT_DIM
    epochs: int = 500
    batch_size: int = 128  # pairs per Adam step
    n_pos: int = 128  # positive pairs per epoch
    n_neg: int = 128  # negative pairs per epoch
    lr: float = 1e-3
    margin: float = DEFAULT_MARGIN
    thresholds: PairThresholds = field(default_factory=PairThresholds)
    hard_negatives: bool = False  # mine each negative among `hard_candidates` with the current network
    hard_candidates: int = 32
    mining_every: int = 1  # recompute the descriptors for mining every this many epochs
    augment: bool = False  # random per-image gain/offset (photometric), see AUGMENT_*
    seed: int = 0
    device: str = "auto"  # "auto" (CUDA when present), "cpu", "cuda", "cuda:1", …
    threads: int | None = None  # torch CPU threads (None: torch's default)
    checkpoint: str | None = None  # file to save to (and resume from)
    checkpoint_every: int = 10
    resume: bool = False
    init_from: str | None = None  # a local checkpoint or state_dict file to start from
    validation: float = VALIDATION_FRACTION  # the last fraction of the frames held out to select the epoch on (0: keep the last)
    validation_margin: int = VALIDATION_MARGIN  # frames before the validation block left out of training as well
    eval_every: int | None = None  # epochs between two recall@1 measurements on the validation block (None: epochs // 10, ≥ 1)
    weight_decay: float = 0.0  # > 0: AdamW with this decoupled weight decay (the paper: Adam, none)
    progress: bool = True

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise InvalidInputError(f"backbone: expected one of {', '.join(BACKBONES)}, got {self.backbone!r}")
        positive = ("dim", "epochs", "batch_size", "hard_candidates", "mining_every", "checkpoint_every")
        for name in positive:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InvalidInputError(f"{name}: expected a positive integer, got {v!r}")
        for name in ("n_pos", "n_neg", "seed", "validation_margin"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise InvalidInputError(f"{name}: expected an integer ≥ 0, got {v!r}")
        if self.seed > MAX_SEED:
            raise InvalidInputError(f"seed: expected at most {MAX_SEED} (torch seeds are 64-bit), got {self.seed!r}")
        if self.n_pos + self.n_neg == 0:
            raise InvalidInputError("n_pos, n_neg: an epoch needs at least one pair")
        for name in ("lr", "margin"):
            v = real_scalar(getattr(self, name), name)
            if not math.isfinite(v) or v <= 0:
                raise InvalidInputError(f"{name}: expected a finite number > 0, got {v!r}")
        if self.lr > MAX_LR:
            raise InvalidInputError(f"lr: expected at most {MAX_LR:g} (Adam moves every weight by about lr per step), got {self.lr!r}")
        if self.eval_every is not None and (isinstance(self.eval_every, bool) or not isinstance(self.eval_every, int) or self.eval_every < 1):
            raise InvalidInputError(f"eval_every: expected a positive integer or None, got {self.eval_every!r}")
        validation = real_scalar(self.validation, "validation")
        if not (math.isfinite(validation) and 0.0 <= validation <= 0.5):
            raise InvalidInputError(f"validation: expected a fraction within [0, 0.5], got {self.validation!r}")
        weight_decay = real_scalar(self.weight_decay, "weight_decay")
        if not (math.isfinite(weight_decay) and weight_decay >= 0.0):
            raise InvalidInputError(f"weight_decay: expected a finite number ≥ 0, got {self.weight_decay!r}")
        if self.resume and not self.checkpoint:
            raise InvalidInputError("resume: needs a checkpoint file to resume from")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1):
            raise InvalidInputError(f"threads: expected a positive integer or None, got {self.threads!r}")

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["thresholds"] = self.thresholds.as_dict()
        return d


@dataclass
class TrainResult:
    """The trained network (eval mode, on the CPU: the selected epoch's when a validation
    block was measured, else the last), the mean loss of every epoch, the seconds each epoch
    took (this run's epochs only), the pair statistics, and the selection: the validation
    curve [(epoch, recall@1)] and the chosen epoch, or why there was none
    (:mod:`.selection`)."""

    model: DescriptorNet
    losses: list[float]
    epoch_seconds: list[float]
    pair_stats: dict[str, Any]
    config: TrainConfig
    selection: dict[str, Any] = field(default_factory=dict)


class ProgressBar:
    """A one-line progress bar on stderr (no dependency)."""

    def __init__(self, total: int, start: int = 0, stream: TextIO | None = None, width: int = 24) -> None:
        self.total, self.done, self.width = total, start, width
        self.stream = stream or sys.stderr
        self._t0, self._start = time.perf_counter(), start

    def update(self, done: int, text: str = "") -> None:
        self.done = done
        frac = done / max(self.total, 1)
        filled = int(round(frac * self.width))
        rate = (time.perf_counter() - self._t0) / max(done - self._start, 1)
        eta = rate * (self.total - done)
        bar = "#" * filled + "." * (self.width - filled)
        self.stream.write(f"\rtrain [{bar}] {done}/{self.total} {text} eta {eta:.0f}s ")
        self.stream.flush()

    def close(self) -> None:
        self.stream.write("\n")
        self.stream.flush()


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise InvalidInputError(f"device: {name!r} is not a torch device") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InvalidInputError(f"device: {name!r} asked for, but CUDA is not available")
    return dev


def _epoch_seed(seed: int, epoch: int) -> int:
    return int(np.random.SeedSequence([seed, epoch, 0x5EED]).generate_state(1, np.uint64)[0] >> 1)


def _augment(x: torch.Tensor) -> torch.Tensor:
    n = x.shape[0]
    gain = torch.exp((torch.rand(n, 1, 1, 1) * 2 - 1) * AUGMENT_LOG_GAIN).to(x.device)
    offset = ((torch.rand(n, 1, 1, 1) * 2 - 1) * AUGMENT_OFFSET).to(x.device)
    return x * gain + offset


def load_network(path: str | os.PathLike[str]) -> DescriptorNet:
    """The network a checkpoint written by :func:`train` holds as its result (the selected
    epoch's, or the last; eval mode, CPU)."""
    ckpt = load_checkpoint(path)
    if "config" not in ckpt:
        raise InvalidInputError(f"checkpoint: {str(path)!r} is a bare state_dict; build the network and load it instead")
    net = DescriptorNet(ckpt["config"]["backbone"], int(ckpt["config"]["dim"]))
    # the run's result: the selected epoch's weights when it measured a validation block
    load_weights(net, ckpt.get("selected_model") or ckpt["model"], str(path))
    return net.eval()


def _save_checkpoint(
    path: Path, model: DescriptorNet, opt: torch.optim.Optimizer, epoch: int, config: TrainConfig, losses: list[float],
    selector: Selector | None,
) -> None:
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "epoch": epoch,
        "config": config.as_dict(),
        "model": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "optimizer": opt.state_dict(),
        "losses": list(losses),
        "selection": None if selector is None else selector.as_dict(),
        "selected_model": None if selector is None else selector.best_state,
    }
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    write_bytes_atomic(path, buffer.getvalue(), "checkpoint")  # a unique temp name: concurrent saves cannot collide


@torch.no_grad()
def embed(model: DescriptorNet, gray: NDArray[np.uint8], device: torch.device | str = "cpu", batch: int = EMBED_BATCH) -> NDArray[np.float32]:
    """Descriptors (N, D) of (N, 224, 224) uint8 images from ``to_gray``, in eval mode
    (the model's mode is restored afterwards)."""
    was_training = model.training
    model.eval()
    out = []
    try:
        for s in range(0, len(gray), batch):
            x = torch.from_numpy(normalize(gray[s : s + batch])).to(device)
            out.append(model(x).float().cpu().numpy())
    finally:
        model.train(was_training)
    dim = model.dim
    return np.concatenate(out) if out else np.zeros((0, dim), np.float32)


def train(
    frames: PosedFrames,
    config: TrainConfig | None = None,
    gray: NDArray[np.uint8] | None = None,
    on_epoch: Callable[[int, float], None] | None = None,
    init_state: dict[str, torch.Tensor] | None = None,
    **overrides: Any,
) -> TrainResult:
    """Train a descriptor network on ``frames`` (posed images, see :mod:`.frames`).

    ``config`` (default: the paper's schedule) with keyword ``overrides`` applied, e.g.
    ``train(seq, backbone="tiny", epochs=20)``. ``gray`` may pass the frames' images already
    through ``to_gray`` ((N, 224, 224) uint8) to skip reading them. ``on_epoch(epoch, loss)``
    is called after each epoch (1-based). ``init_state``: the weights of ``init_from`` as
    :func:`.pretrained.load_checkpoint` already read them (``["model"]``; the file is then not
    read again).
    """
    cfg = replace(config or TrainConfig(), **overrides)
    if len(frames) < 2:
        raise InvalidInputError(f"frames: training needs at least 2 posed images, got {len(frames)}")
    poses = poses_of(frames)
    if gray is None:
        gray = gray_images(frames)
    elif gray.shape != (len(frames), 224, 224) or gray.dtype != np.uint8:
        raise InvalidInputError(f"gray: expected ({len(frames)}, 224, 224) uint8, got {gray.dtype} {gray.shape}")
    split = split_validation(len(frames), cfg.validation, cfg.validation_margin)
    sampler = PairSampler(poses[split.train], cfg.thresholds, cfg.seed)
    selector = Selector(split, poses, gray) if split.active else None

    device = _device(cfg.device)
    if device.type == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    previous_threads = torch.get_num_threads()
    previous_deterministic = torch.are_deterministic_algorithms_enabled()
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    previous_fill = torch.utils.deterministic.fill_uninitialized_memory  # type: ignore[attr-defined]
    torch.use_deterministic_algorithms(True, warn_only=True)
    # deterministic mode also NaN-fills every new buffer (a debugging aid that costs ~20 %
    # of a CPU step here); results do not depend on it
    torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]
    try:
        result = _run(cfg, gray[split.train], sampler, device, on_epoch, selector, init_state)
        result.selection = {"why": split.why} if selector is None else selector.as_dict()
        return result
    finally:
        torch.utils.deterministic.fill_uninitialized_memory = previous_fill  # type: ignore[attr-defined]
        torch.use_deterministic_algorithms(previous_deterministic)
        torch.set_num_threads(previous_threads)


def _run(
    cfg: TrainConfig,
    gray: NDArray[np.uint8],
    sampler: PairSampler,
    device: torch.device,
    on_epoch: Callable[[int, float], None] | None,
    selector: Selector | None,
    init_state: dict[str, torch.Tensor] | None = None,
) -> TrainResult:
    torch.manual_seed(cfg.seed)
    model = build_network(cfg.backbone, cfg.dim)  # type: ignore[arg-type]
    if cfg.init_from:
        init_weights(model, cfg.init_from, init_state)
    model.to(device)
    opt: torch.optim.Optimizer = (
        torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        if cfg.weight_decay > 0
        else torch.optim.Adam(model.parameters(), lr=cfg.lr)
    )
    losses: list[float] = []
    start = 0
    ckpt_path = Path(cfg.checkpoint) if cfg.checkpoint else None
    if cfg.resume and ckpt_path is not None:
        ckpt = load_checkpoint(ckpt_path)
        if "config" not in ckpt:
            raise InvalidInputError(f"resume: {str(ckpt_path)!r} is not a checkpoint written by geoloc train")
        for key in ("backbone", "dim"):
            if ckpt["config"][key] != getattr(cfg, key):
                raise InvalidInputError(f"resume: the checkpoint has {key} {ckpt['config'][key]!r}, this run {getattr(cfg, key)!r}")
        load_weights(model, ckpt["model"], str(ckpt_path))
        opt.load_state_dict(ckpt["optimizer"])
        start, losses = int(ckpt["epoch"]), [float(x) for x in ckpt["losses"]]
        if selector is not None and ckpt.get("selection"):
            selector.restore(ckpt["selection"], ckpt.get("selected_model"))

    bar = ProgressBar(cfg.epochs, start) if cfg.progress else None
    every = cfg.eval_every or max(1, cfg.epochs // MEASUREMENTS)
    epoch_seconds = []
    descriptors = None
    model.train()
    for epoch in range(start, cfg.epochs):
        t0 = time.perf_counter()
        torch.manual_seed(_epoch_seed(cfg.seed, epoch))
        if cfg.hard_negatives and (descriptors is None or epoch % cfg.mining_every == 0):
            descriptors = embed(model, gray, device)
        pairs = sampler.sample(epoch, cfg.n_pos, cfg.n_neg, descriptors, cfg.hard_candidates)
        order = sampler.rng(epoch).permutation(len(pairs))  # mix positives and negatives
        total = 0.0
        for s in range(0, len(order), cfg.batch_size):
            sel = order[s : s + cfg.batch_size]
            n = len(sel)
            idx = np.concatenate([pairs.first[sel], pairs.second[sel]])
            x = torch.from_numpy(normalize(gray[idx])).to(device)
            if cfg.augment:
                x = _augment(x)
            y = torch.from_numpy(pairs.label[sel]).to(device)
            z = model(x)  # both twins in one pass: the same weights by construction
            loss = contrastive_loss(z[:n], z[n:], y, cfg.margin)
            opt.zero_grad(set_to_none=True)
            loss.backward()  # type: ignore[no-untyped-call]
            opt.step()
            total += float(loss.detach()) * n
        mean = total / len(order)
        if not np.isfinite(mean):
            # the learning rate is what diverged it (no weights are written): a user's error to
            # correct, named as such
            raise InvalidInputError(f"lr: the loss became {mean} at epoch {epoch + 1} with lr = {cfg.lr:g}; lower it")
        losses.append(mean)
        epoch_seconds.append(time.perf_counter() - t0)
        done = epoch + 1
        text = f"loss {mean:.4f}"
        if selector is not None and (done % every == 0 or done == cfg.epochs):
            recall = selector.recall_at_1(embed(model, selector.gray, device))
            selector.record(done, recall, model)
            text += f" val recall@1 {100 * recall:.1f} %"
        if ckpt_path is not None and (done % cfg.checkpoint_every == 0 or done == cfg.epochs):
            _save_checkpoint(ckpt_path, model, opt, done, cfg, losses, selector)
        if bar is not None:
            bar.update(done, text)
        if on_epoch is not None:
            on_epoch(done, mean)
    if bar is not None:
        bar.close()
    model.eval().cpu()
    if selector is not None and selector.best_state is not None:
        model.load_state_dict(selector.best_state)
    return TrainResult(model, losses, epoch_seconds, sampler.stats(), cfg)

"""Train the range-image network from labelled bags (``topometric train``).

Scans are projected once into a cache (data.py). Each step takes random azimuth crops of random scans of one
sensor model (every model an equal share of the steps unless ``shares`` sets some; on a GPU the cache sits in
its memory and the crops are cut there), augments them (yaw = azimuth roll, mirror, sensor height and tilt
jitter, range noise, point dropout, intensity scale / absence) and minimises weighted cross entropy +
Lovász-softmax. Crops are trained with zero azimuth padding (their ends do not meet); validation and inference
use whole scans with circular padding. With validation bags the epoch of best validation mIoU (paper classes,
the mean over sensor models) is saved, else the last (test bags are never read). ``max_minutes`` bounds the
run: the cosine learning-rate decay then follows max(step fraction, time fraction) and training stops cleanly
when the time is up.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch.nn import functional as F

from .. import classes as C
from ..reports import write_json
from .checkpoint import FORMAT_VERSION, build_model, load_weights, save_weights, state_digest, torch_device
from .data import load_or_build_cache
from .metrics import confusion, iou_per_class, miou
from .model import ModelSpec, RangeNet, count_parameters
from .projection import CHANNELS, MAX_ROWS



@dataclass
class TrainConfig:
    """Training hyper-parameters (all recorded in the model card)."""

    epochs: int = 12
    crops_per_epoch: int = 768  # random azimuth crops per epoch
    batch: int = 12
    crop_width: int = 480  # columns per crop (multiple of 2 × fold)
    lr: float = 4e-3  # AdamW peak learning rate, cosine decay after a short warm-up
    weight_decay: float = 1e-4
    lovasz: float = 1.0  # weight of the Lovász-softmax term
    lovasz_pixels: int = 40000  # Lovász on this many random labelled pixels per batch (sorting is costly)
    every: int = 3  # use every n-th scan of each bag
    val_every: int = 4  # use every n-th scan of each validation bag
    seed: int = 0
    threads: int = 1  # torch CPU threads (more than the free cores makes OpenMP crawl on a shared machine)
    device: str = "cpu"  # cpu, cuda (cuda:N) or auto (cuda when there is one); the saved weights are CPU tensors
    workers: int = 1  # processes that project the bags into the cache (its first build only)
    height_jitter: float = 0.1  # m, uniform ± sensor height change
    tilt_deg: float = 1.5  # deg, std of sensor roll / pitch jitter
    range_noise: float = 0.01  # m, std of extra range noise
    max_dropout: float = 0.05  # up to this fraction of points removed
    no_intensity: float = 0.1  # probability a crop has no intensity (clouds without the field)
    max_minutes: float = 0.0  # min, wall-clock budget of the training loop (0 = none; epochs bound it)
    shares: dict = field(default_factory=dict)  # sensor model -> its share of the batches (0..1); the rest equal


def class_weights(labels: np.ndarray, num_classes: int = C.NUM_CLASSES, cap: float = 10.0) -> np.ndarray:
    """(K,) 1/sqrt(frequency) of each class in ``labels`` (255 ignored), mean 1 over present classes, capped."""
    counts = np.bincount(labels[labels < num_classes].ravel(), minlength=num_classes).astype(np.float64)
    freq = counts / max(counts.sum(), 1)
    w = np.where(freq > 0, 1.0 / np.sqrt(np.maximum(freq, 1e-12)), 0.0)
    w /= w[freq > 0].mean()
    return np.minimum(w, cap).astype(np.float32)


def lovasz_softmax(probs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Lovász-softmax loss (Berman et al. 2018) of probabilities (P, K) vs labels (P,), classes present only."""
    losses = []
    for c in range(probs.shape[1]):
        fg = (labels == c).float()
        if fg.sum() == 0:
            continue
        errors = (fg - probs[:, c]).abs()
        errors_sorted, perm = torch.sort(errors, descending=True)
        fg_sorted = fg[perm]
        gts = fg_sorted.sum()
        intersection = gts - fg_sorted.cumsum(0)
        union = gts + (1 - fg_sorted).cumsum(0)
        jaccard = 1.0 - intersection / union
        jaccard = torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]])
        losses.append(torch.dot(errors_sorted, jaccard))
    return torch.stack(losses).mean() if losses else probs.sum() * 0


def network_input(xyz: torch.Tensor, intensity: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, 6, H, W) input in projection.CHANNELS order from xyz (B, 3, H, W), intensity (B, 1, H, W), valid (B, H, W)."""
    v = valid.unsqueeze(1).to(xyz.dtype)
    xyz = xyz * v
    rng = torch.linalg.vector_norm(xyz, dim=1, keepdim=True)
    return torch.cat([rng, xyz, intensity * v, v], 1)


@dataclass(frozen=True, eq=False)
class Stratum:
    """The images of one sensor model in one image-shape group of the cache."""

    group: int  # index of the group in the list of groups
    sensor: str
    images: np.ndarray  # (n,) indices of this sensor's images in the group


def sensor_strata(groups: Sequence[dict], shares: dict | None = None) -> tuple[list[Stratum], np.ndarray]:
    """The (group, sensor) strata of the cache and each one's chance per batch: every sensor model gets an
    equal share, split over its strata by image count. (A share per image shape would give the ten Ouster
    models, one 32 x 1024 shape, one share together and a VLP-16 one alone; and a non-repetitive scan's
    image width follows its point count, so the Mid-360 fills several groups, some of one odd-width scan.)
    ``shares``: sensor model -> its own share of the batches (0..1); the other models split the rest equally.
    ValueError for a model not in the cache, shares over 1, or named shares of 1 with other models left."""
    strata = [Stratum(i, str(s), np.flatnonzero(g["sensor"] == s))
              for i, g in enumerate(groups) for s in np.unique(g["sensor"])]
    per_sensor: dict[str, int] = {}
    for st in strata:
        per_sensor[st.sensor] = per_sensor.get(st.sensor, 0) + len(st.images)
    model_share = _model_shares(sorted(per_sensor), shares or {})
    p = np.array([model_share[st.sensor] * len(st.images) / per_sensor[st.sensor] for st in strata])
    return strata, p / p.sum()


def _model_shares(models: Sequence[str], shares: dict) -> dict:
    """Each sensor model's share of the batches: the named ones as given, the rest split equally."""
    unknown = sorted(set(shares) - set(models))
    if unknown:
        raise ValueError(f"--share names sensor model(s) not in the training bags: {', '.join(unknown)} "
                         f"(they hold {', '.join(models)})")
    named, rest = sum(shares.values()), [m for m in models if m not in shares]
    if any(not 0 <= v <= 1 for v in shares.values()) or named > 1 + 1e-9 or (rest and named >= 1 - 1e-9) \
            or (not rest and abs(named - 1) > 1e-9):
        raise ValueError(f"--share: each share must be in 0..1, the named ones {named:g} in all, leaving more than "
                         f"0 for the {len(rest)} other model(s) (or exactly 1 when every model is named)")
    return {m: shares.get(m, (1 - named) / max(len(rest), 1)) for m in models}


def strata_summary(groups: Sequence[dict], strata: Sequence[Stratum], chances: np.ndarray) -> str:
    """One line per sensor model: its share of the batches, image count and image shapes."""
    sensors = sorted({st.sensor for st in strata})
    lines = [f"training batches by sensor model ({len(sensors)}):"]
    for name in sensors:
        idx = [i for i, st in enumerate(strata) if st.sensor == name]
        shapes = ", ".join("x".join(map(str, groups[strata[i].group]["images"].shape[-2:])) for i in idx)
        lines.append(f"  {100 * chances[idx].sum():5.1f} %  {sum(len(strata[i].images) for i in idx):6d} images "
                     f"({shapes}): {name}")
    return "\n".join(lines)


def sample_crops(groups: Sequence[dict], n: int, width: int, rng: np.random.Generator,
                 strata: tuple[list[Stratum], np.ndarray] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """n random azimuth crops (wrapping around) of random images of ONE sensor model in one image-shape group,
    the stratum drawn by its chance (default: :func:`sensor_strata`): xyz+intensity (n, 4, rows, w) float32 and
    labels (n, rows, w) int64, on the device the group's images are on (numpy arrays: the CPU); w = width or
    the group's own width when that is narrower. The random draws come from ``rng`` alone."""
    found, p = sensor_strata(groups) if strata is None else strata
    st = found[int(rng.choice(len(found), p=p))]
    images, labels = (torch.as_tensor(groups[st.group][k]) for k in ("images", "labels"))
    _, ch, rows, cols_n = images.shape
    w = min(width, cols_n)
    idx = st.images[rng.integers(len(st.images), size=n)]
    start = rng.integers(cols_n, size=n)
    dev = images.device
    cols = torch.from_numpy((start[:, None] + np.arange(w)) % cols_n).to(dev)[:, None, None, :]
    i = torch.from_numpy(idx).to(dev)[:, None, None, None]
    c, r = torch.arange(ch, device=dev)[None, :, None, None], torch.arange(rows, device=dev)[None, None, :, None]
    return images[i, c, r, cols].float(), labels[i[:, 0], r[:, 0], cols[:, 0]].long()


def confusion_on(truth: torch.Tensor, pred: torch.Tensor, num_classes: int = C.NUM_CLASSES) -> torch.Tensor:
    """metrics.confusion on the tensors' own device: (K, K) int64 counts, rows = truth; labels >= K ignored."""
    keep = (truth < num_classes) & (pred < num_classes)
    idx = truth[keep] * num_classes + pred[keep]
    return torch.bincount(idx, minlength=num_classes * num_classes).view(num_classes, num_classes)


def augment(x: torch.Tensor, y: torch.Tensor, cfg: TrainConfig, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Augment a batch of crops (see module docstring); returns the network input and labels (255 = ignore).
    The crops and the generator ``g`` are on one device; the random draws are made there."""
    b, dev = x.shape[0], g.device
    xyz, inten = x[:, :3], x[:, 3:4]
    valid = y != 255

    def rand(*shape):
        return torch.rand(*shape, generator=g, device=dev)

    def uniform(lo, hi, *shape):
        return lo + (hi - lo) * rand(*shape)

    yaw = uniform(0, 2 * math.pi, b)
    mirror = rand(b) < 0.5
    roll, pitch = (torch.randn(2, b, generator=g, device=dev) * math.radians(cfg.tilt_deg)).unbind(0)
    rot = _rotation(yaw, roll, pitch)
    rot[mirror] = rot[mirror] * torch.tensor([1.0, -1.0, 1.0], device=dev).view(1, 3)  # y -> -y; columns flip below
    xyz = torch.einsum("bij,bjhw->bihw", rot, xyz)
    xyz[:, 2] += uniform(-cfg.height_jitter, cfg.height_jitter, b).view(b, 1, 1)
    r = torch.linalg.vector_norm(xyz, dim=1, keepdim=True).clamp_min(1e-3)
    xyz = xyz * (1 + cfg.range_noise * torch.randn(r.shape, generator=g, device=dev) / r)
    inten = inten * uniform(0.8, 1.2, b).view(b, 1, 1, 1) * (rand(b) >= cfg.no_intensity).view(b, 1, 1, 1)
    drop = rand(*valid.shape) < uniform(0, cfg.max_dropout, b).view(b, 1, 1)
    valid = valid & ~drop
    y = torch.where(valid, y, torch.full_like(y, 255))
    inp = network_input(xyz, inten, valid)
    inp[mirror] = inp[mirror].flip(-1)
    y[mirror] = y[mirror].flip(-1)
    return inp, y


def _rotation(yaw: torch.Tensor, roll: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = yaw.cos(), yaw.sin(), pitch.cos(), pitch.sin(), roll.cos(), roll.sin()
    one, zero = torch.ones_like(yaw), torch.zeros_like(yaw)
    rz = torch.stack([cy, -sy, zero, sy, cy, zero, zero, zero, one], 1).view(-1, 3, 3)
    ry = torch.stack([cp, zero, sp, zero, one, zero, -sp, zero, cp], 1).view(-1, 3, 3)
    rx = torch.stack([one, zero, zero, zero, cr, -sr, zero, sr, cr], 1).view(-1, 3, 3)
    return rz @ ry @ rx


def training_device(name: str) -> torch.device:
    """The torch device of ``TrainConfig.device``: auto = the first CUDA device when there is one, else the CPU;
    otherwise as checkpoint.torch_device (SegmentationError, a ValueError, for an unknown or missing device)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch_device(name, "training device", "cpu, cuda, cuda:N or auto")


@torch.inference_mode()
def evaluate_cache(model: RangeNet, groups: Sequence[dict], batch: int = 4) -> dict[str, np.ndarray]:
    """Confusion matrix per sensor model of the model on whole cached images of every shape group (circular
    padding), on the model's device."""
    model.eval().set_circular(True)
    dev = next(model.parameters()).device
    conf: dict[str, np.ndarray] = {}
    for g in groups:
        images, labels, sensors = g["images"], g["labels"], np.asarray(g["sensor"])
        for i in range(0, len(images), batch):
            x = torch.from_numpy(images[i:i + batch].astype(np.float32)).to(dev)
            y = labels[i:i + batch]
            inp = network_input(x[:, :3], x[:, 3:4], torch.from_numpy(y != 255).to(dev))
            pred = model(inp).argmax(1).cpu().numpy()
            for name in np.unique(sensors[i:i + batch]):
                on = sensors[i:i + batch] == name
                conf[str(name)] = conf.get(str(name), 0) + confusion(y[on], pred[on])
    return conf


def validation_entry(conf: dict[str, np.ndarray]) -> dict:
    """An epoch's validation record from per-sensor confusion matrices: ``val_miou``, the mean over sensor models
    of each one's mIoU (paper classes; the goal is per sensor, and pooled pixels would let the 128-beam models
    outweigh a 16-beam one eight to one; a model whose scans show none of those classes is left out),
    ``val_miou_by_sensor``, and ``val_iou`` per class of the pooled pixels."""
    by_sensor = {name: round(miou(c), 4) for name, c in sorted(conf.items())}
    pooled = sum(conf.values())
    return {"val_miou": round(float(np.nanmean(list(by_sensor.values()))), 4), "val_miou_by_sensor": by_sensor,
            "val_iou": {C.NAMES[c]: round(float(v), 4) for c, v in enumerate(iou_per_class(pooled))}}


def model_card(spec: ModelSpec, cfg: TrainConfig, bags: Sequence[str], val_bags: Sequence[str], command: str,
               history: list[dict], n_scans: int, n_params: int, elapsed_s: float, selected_epoch: int = 0,
               init: dict | None = None) -> dict:
    """The JSON model card: classes, input spec, training data and settings, metrics of the saved epoch
    (``selected_epoch``, 1-based; 0 = the last); ``init``: what the run started from (see :func:`init_record`)."""
    last = history[selected_epoch - 1] if selected_epoch else (history[-1] if history else {})
    return {
        "name": "rangenet", "format_version": FORMAT_VERSION,
        "classes": list(C.NAMES), "paper_classes": [C.NAMES[c] for c in C.PAPER_CLASSES],
        "model": spec.as_dict(), "parameters": n_params,
        "input": {"channels": list(CHANNELS),
                  "rows": "the scan grid's rows (grid.py: 0 = lowest beam), split into interleaved images of at "
                          f"most {MAX_ROWS} rows, padded to a multiple of 4",
                  "columns": "the scan grid's azimuth cells (firings per revolution, a multiple of 8), column 0 "
                             "centred on +x, counter-clockwise",
                  "units": "range/x/y/z in m (sensor frame), intensity 0..255, valid 0/1"},
        "training": {"command": command, "bags": [str(b) for b in bags], "val_bags": [str(b) for b in val_bags],
                     "scans": n_scans, "seed": cfg.seed, "config": asdict(cfg), "elapsed_s": round(elapsed_s, 1),
                     "selected_epoch": last.get("epoch", 0), "init": init,
                     "torch": str(torch.__version__), "history": history},
        "metrics": {"val": {k: last[k] for k in ("val_miou", "val_miou_by_sensor", "val_iou") if k in last}},
    }


def init_record(path: str | Path, card: dict, state: dict) -> dict:
    """What a fine-tuning run started from, for its model card: the file, its tensors' digest, and the
    parent's own training command, seed, time and validation result (so the chain can be rerun)."""
    parent = card.get("training", {})
    return {"weights": str(path), "state_sha256": state_digest(state), "command": parent.get("command"),
            "seed": parent.get("seed"), "elapsed_s": parent.get("elapsed_s"),
            "selected_epoch": parent.get("selected_epoch"), "val": card.get("metrics", {}).get("val"),
            "init": parent.get("init")}


def train(bags: Sequence[str | Path], out: str | Path, cfg: TrainConfig = TrainConfig(), spec: ModelSpec = ModelSpec(),
          val_bags: Sequence[str | Path] = (), cache_dir: str | Path = "data/cache", command: str = "",
          progress: bool = True, init: str | Path | None = None) -> dict:
    """Train on labelled ``bags``; write OUT/rangenet.pt (state dict + card) and OUT/model_card.json.

    ``init``: a weights file (checked as the Segmenter checks it) to start from instead of random weights
    (fine-tuning); its network (model card) replaces ``spec``. Returns the model card. With validation bags
    the weights of the epoch with the best validation mIoU are saved (ties: the later one), else the last
    epoch's.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    if cfg.crop_width % (2 * spec.fold):
        raise ValueError(f"crop_width {cfg.crop_width} must be a multiple of {2 * spec.fold}")
    if init:  # checked before the cache is built (minutes to hours on a real training set)
        init_card, init_state = load_weights(init)
    dev = training_device(cfg.device)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    g = torch.Generator(device=dev).manual_seed(cfg.seed)
    data = load_or_build_cache(bags, cache_dir, cfg.every, progress=progress, workers=cfg.workers)
    val = (load_or_build_cache(val_bags, cache_dir, cfg.val_every, progress=progress, workers=cfg.workers)
           if val_bags else None)
    groups = list(data.values())
    strata = sensor_strata(groups, cfg.shares)
    if progress:
        tqdm.write(strata_summary(groups, *strata))
    val_groups = list(val.values()) if val is not None else None
    weights = torch.from_numpy(class_weights(np.concatenate([g["labels"].reshape(-1) for g in groups])))
    if init:
        model, started = build_model(init_card, init_state, str(init)), init_record(init, init_card, init_state)
        spec = model.spec
    else:
        model, started = RangeNet(spec), None
    model, weights = model.to(dev), weights.to(dev)
    if dev.type == "cuda" and _fits_on(dev, groups):  # crops are cut on the GPU: the images go there once
        groups = [{**g, "images": torch.from_numpy(g["images"]).to(dev), "labels": torch.from_numpy(g["labels"]).to(dev)}
                  for g in groups]
    benchmark = torch.backends.cudnn.benchmark
    torch.backends.cudnn.benchmark = dev.type == "cuda"  # few input shapes (one per image-shape group)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        model, history, selected = _train_loop(model, weights, groups, strata, val_groups, cfg, rng, g, out, progress)
    finally:
        torch.backends.cudnn.benchmark = benchmark
    card = model_card(spec, cfg, [str(b) for b in bags], [str(b) for b in val_bags], command, history,
                      sum(len(g["images"]) for g in groups), count_parameters(model), time.perf_counter() - t0,
                      selected, started)
    save_weights(model, card, out)
    return card


def _fits_on(dev: torch.device, groups: Sequence[dict], share: float = 0.6) -> bool:
    """Whether the cached images and labels take at most ``share`` of the GPU's free memory (the rest is for
    the network's activations); when not, crops are cut on the CPU and copied over."""
    free, _ = torch.cuda.mem_get_info(dev)
    need = sum(g["images"].nbytes + g["labels"].nbytes for g in groups)
    return need <= share * free


def _train_loop(model: RangeNet, weights: torch.Tensor, groups: Sequence[dict], strata, val_groups, cfg: TrainConfig,
                rng: np.random.Generator, g: torch.Generator, out: Path, progress: bool) -> tuple[RangeNet, list, int]:
    """The optimisation loop of :func:`train` (its arguments as set up there, on the model's device; OUT gets
    train_log.json after every epoch): (the model on the CPU with the saved epoch's weights, the history, that
    epoch (1-based; 0 = the last))."""
    from tqdm import tqdm

    dev = next(model.parameters()).device
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = max(1, cfg.crops_per_epoch // cfg.batch)
    total = steps_per_epoch * cfg.epochs
    warmup = min(100, total // 10)
    budget_s = 60.0 * cfg.max_minutes
    t_loop = time.perf_counter()

    def done_fraction(step: int) -> float:
        """Fraction of the run done: by steps, or by the time budget when that is further along."""
        done = (step - warmup) / max(1, total - warmup)
        if budget_s > 0:
            done = max(done, (time.perf_counter() - t_loop) / budget_s)
        return min(1.0, done)

    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: (s + 1) / warmup if s < warmup else 0.5 * (1 + math.cos(math.pi * done_fraction(s))))
    history, best, best_state = [], -1.0, None
    for epoch in range(cfg.epochs):
        if epoch and budget_s > 0 and time.perf_counter() - t_loop >= budget_s:
            break  # (the first epoch always runs at least one step)
        model.train().set_circular(False)
        conf = torch.zeros((C.NUM_CLASSES, C.NUM_CLASSES), dtype=torch.int64, device=dev)
        losses = []  # tensors on the device: no copy back to the CPU at every step
        te = time.perf_counter()
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="step", disable=not progress,
                   leave=False)
        for step in bar:
            x, y = sample_crops(groups, cfg.batch, cfg.crop_width, rng, strata)
            inp, y = augment(x.to(dev), y.to(dev), cfg, g)
            logits = model(inp)
            loss = F.cross_entropy(logits, y, weight=weights, ignore_index=255)
            if cfg.lovasz > 0:
                yf = y.reshape(-1)
                keep = torch.nonzero(yf != 255).squeeze(1)
                keep = keep[torch.randperm(len(keep), generator=g, device=dev)[:cfg.lovasz_pixels]]
                probs = logits.softmax(1).permute(0, 2, 3, 1).reshape(-1, logits.shape[1])[keep]
                loss = loss + cfg.lovasz * lovasz_softmax(probs, yf[keep])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.detach())
            conf += confusion_on(y, logits.detach().argmax(1))
            if step % 20 == 19:
                bar.set_postfix(loss=f"{torch.stack(losses[-20:]).mean().item():.3f}")
            if budget_s > 0 and time.perf_counter() - t_loop >= budget_s:
                break  # time is up: finish this (partial) epoch with its validation
        entry = {"epoch": epoch + 1, "loss": round(torch.stack(losses).mean().item(), 4),
                 "train_miou": round(miou(conf.cpu().numpy()), 4),
                 "lr": opt.param_groups[0]["lr"], "seconds": round(time.perf_counter() - te, 1)}
        if val_groups is not None:
            entry.update(validation_entry(evaluate_cache(model, val_groups)))
            if entry["val_miou"] >= best:
                best = entry["val_miou"]
                best_state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
                entry["best"] = True
        history.append(entry)
        val_text = f" val mIoU {100 * entry['val_miou']:.2f}" if "val_miou" in entry else ""
        tqdm.write(f"epoch {epoch + 1:2d}: loss {entry['loss']:.4f} train mIoU {100 * entry['train_miou']:.2f}"
                   f"{val_text} ({entry['seconds']:.0f} s)")
        write_json(out / "train_log.json", history, indent=2)
    selected = 0
    model = model.cpu()
    if best_state is not None:
        model.load_state_dict(best_state)
        selected = max(e["epoch"] for e in history if e.get("best"))
    return model, history, selected

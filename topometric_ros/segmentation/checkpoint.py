"""The weights file of the segmentation network: what infer.py loads and train.py writes.

A weights file is a torch file {'model_card': dict, 'state_dict': tensors, 'state_sha256': digest} read with
``torch.load(weights_only=True)`` (no arbitrary code runs), checked key by key and shape by shape against
the net the card describes; a model_card.json beside it may pin the file's sha256. Any problem raises
SegmentationError with the reason.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch

from .. import classes as C
from ..reports import written_whole
from .model import ModelSpec, RangeNet

WEIGHTS_NAME, CARD_NAME = "rangenet.pt", "model_card.json"
FORMAT_VERSION = 1
SHIPPED = Path(__file__).resolve().parent / "weights" / WEIGHTS_NAME


class SegmentationError(ValueError):
    """Weights that are missing, unreadable, tampered with or do not fit the network; bad device."""


def torch_device(name: str, what: str = "device", choices: str = "cpu or cuda") -> torch.device:
    """The torch device ``name`` (cpu, cuda or cuda:N) names, for the network to run or train on.
    Raises SegmentationError for another name or a CUDA device torch does not see; ``what`` and ``choices``
    word the message."""
    try:
        dev = torch.device(name) if name in ("cpu", "cuda") or name.startswith("cuda:") else None
    except RuntimeError:
        dev = None
    if dev is None:
        raise SegmentationError(f"unknown {what} {name!r}; use {choices}")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SegmentationError(f"{what} {name!r} requested but torch sees no CUDA device here")
    return dev


def one_line_reason(e: Exception) -> str:
    """'ExceptionName: first line of its message', for a one-line error or warning."""
    return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"


def load_weights(path: str | Path) -> tuple[dict, dict]:
    """(model card, state dict) of a weights file, loaded without executing code."""
    path = Path(path)
    if path.is_dir():
        raise SegmentationError(f"segmentation weights {path} is a folder; give the weights file in it "
                                f"({path / WEIGHTS_NAME})")
    if not path.is_file():
        raise SegmentationError(f"segmentation weights not found: {path}")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # UnpicklingError, RuntimeError (zip), EOFError, ... for garbage or unsafe pickles
        raise SegmentationError(f"cannot load segmentation weights {path}: not a safe torch weights file "
                                f"({one_line_reason(e)})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("model_card"), dict) or not isinstance(doc.get("state_dict"), dict):
        raise SegmentationError(f"{path}: expected {{'model_card': dict, 'state_dict': dict}}, got {type(doc).__name__}"
                                + (f" with keys {sorted(map(str, doc))}" if isinstance(doc, dict) else ""))
    _check_checksum(path)
    state = doc["state_dict"]
    bad = [str(k) for k, v in state.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise SegmentationError(f"{path}: state dict entries that are not named tensors: {bad[:5]}")
    _check_state_digest(state, doc.get("state_sha256"), str(path))
    return doc["model_card"], state


def _check_state_digest(state: dict, digest: object, source: str) -> None:
    """The tensors must hash to the digest saved with them (catches modified or corrupted weights)."""
    if not isinstance(digest, str):
        raise SegmentationError(f"{source}: no state_sha256 digest; not a weights file written by topometric train")
    if state_digest(state) != digest:
        raise SegmentationError(f"{source}: tensor checksum mismatch; the weights were modified or corrupted")


def _check_checksum(path: Path) -> None:
    """When a model_card.json next to the weights names their sha256, the file must match it."""
    card_path = path.parent / CARD_NAME
    if not card_path.is_file():
        return
    try:
        want = json.loads(card_path.read_text()).get("weights", {})
    except (json.JSONDecodeError, AttributeError):
        raise SegmentationError(f"{card_path}: not a valid model card (JSON)") from None
    if want.get("file") == path.name and want.get("sha256"):
        got = hashlib.sha256(path.read_bytes()).hexdigest()
        if got != want["sha256"]:
            raise SegmentationError(f"{path}: sha256 {got[:12]}… does not match {card_path} ({want['sha256'][:12]}…); "
                                    "the weights were modified")


def build_model(card: dict, state: dict, source: str = "weights") -> RangeNet:
    """The network the card describes with ``state`` loaded, after checking every key and shape."""
    if card.get("format_version") != FORMAT_VERSION:
        raise SegmentationError(f"{source}: model card format {card.get('format_version')!r}, expected {FORMAT_VERSION}")
    if list(card.get("classes", [])) != list(C.NAMES):
        raise SegmentationError(f"{source}: classes {card.get('classes')} differ from {list(C.NAMES)}")
    try:
        spec = ModelSpec.from_dict(card["model"])
        model = RangeNet(spec)
    except Exception as e:  # wrong types or sizes in the card
        raise SegmentationError(f"{source}: model card does not describe a valid network: {e}") from None
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing or extra:
        raise SegmentationError(f"{source}: state dict does not fit the network: missing {missing[:5]}, "
                                f"unexpected {extra[:5]}")
    for k, v in expected.items():
        got = state[k]
        if not isinstance(got, torch.Tensor) or got.shape != v.shape or got.dtype != v.dtype:
            desc = f"{tuple(got.shape)} {got.dtype}" if isinstance(got, torch.Tensor) else type(got).__name__
            raise SegmentationError(f"{source}: tensor {k!r} is {desc}, the network needs {tuple(v.shape)} {v.dtype}")
        if v.is_floating_point() and not torch.isfinite(got).all():
            raise SegmentationError(f"{source}: tensor {k!r} has non-finite values")
    model.load_state_dict(state)
    return model.eval().set_circular(True)


def state_digest(state: dict) -> str:
    """sha256 over the names, dtypes, shapes and bytes of a state dict's tensors (sorted by name)."""
    h = hashlib.sha256()
    for k in sorted(state):
        v = state[k].detach().cpu().contiguous()
        h.update(f"{k}|{v.dtype}|{tuple(v.shape)}|".encode())
        h.update(v.reshape(-1).view(torch.uint8).numpy().tobytes() if v.numel() else b"")
    return h.hexdigest()


def beside(weights: str | Path, name: str) -> Path:
    """The file ``name`` beside a weights file (its int8 ranges, its non-repetitive statistics)."""
    return Path(weights).parent / name


def read_beside(weights: str | Path, name: str, fmt: int, key: str, state_sha256: str, what: str,
                command: str) -> tuple[dict | None, str]:
    """(the JSON document ``name`` beside ``weights``, "") when it is of format ``fmt``, holds a dict under ``key``
    and was made for the weights whose tensors hash to ``state_sha256``; else (None, why not). ``what`` names
    the file's content and ``command`` the command that makes it, for the reasons."""
    path = beside(weights, name)
    if not path.is_file():
        return None, f"no {what} beside the weights ({name}; make them with {command})"
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        return None, f"{path}: not readable JSON ({e})"
    if not isinstance(doc, dict) or doc.get("format_version") != fmt or not isinstance(doc.get(key), dict):
        return None, f"{path}: not a file of {what} of format {fmt}"
    if doc.get("state_sha256") != state_sha256:
        return None, f"{path} was made for other weights; run {command} for these"
    return doc, ""


def write_beside(weights: str | Path, name: str, doc: dict, indent: int | None = None) -> Path:
    """Write the JSON document ``doc`` whole as ``name`` beside ``weights``; returns its path."""
    path = beside(weights, name)
    with written_whole(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=indent) + "\n")
    return path


def save_weights(model: RangeNet, card: dict, out: str | Path) -> Path:
    """OUT/rangenet.pt = {'model_card': card, 'state_dict': tensors, 'state_sha256': digest of the tensors};
    OUT/model_card.json = card + the file's sha256."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / WEIGHTS_NAME
    state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    card = json.loads(json.dumps(card))  # plain types only: what torch.load(weights_only=True) accepts
    with written_whole(path) as tmp:
        torch.save({"model_card": card, "state_dict": state, "state_sha256": state_digest(state)}, tmp)
    doc = {**card, "weights": {"file": WEIGHTS_NAME, "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                               "bytes": path.stat().st_size}}
    (out / CARD_NAME).write_text(json.dumps(doc, indent=2))
    return path


def blend_weights(parent: str | Path, tuned: str | Path, alpha: float, out: str | Path, command: str = "") -> Path:
    """OUT/rangenet.pt = (1 - alpha) × parent + alpha × tuned, tensor by tensor (counters from ``tuned``):
    a fine-tune blended with the weights it started from (WiSE-FT, Wortsman et al., CVPR 2022), which keeps
    most of the fine-tune's gains while giving back less of what the parent did well. Both files must hold
    the same network. The card is the tuned one's, with the blend recorded (the parent by path and by its
    tensors' digest, which names it even once the file is replaced; whether the tuned run started from it)
    and its validation result dropped (it was the tuned weights'). Returns the path."""
    if not 0.0 <= alpha <= 1.0:
        raise SegmentationError(f"blend alpha must be within [0, 1], got {alpha}")
    target = Path(out) / WEIGHTS_NAME
    for role, given in (("parent", parent), ("tuned", tuned)):
        if target.exists() and Path(given).exists() and os.path.samefile(given, target):  # links, hard links too
            raise SegmentationError(f"the output folder {out} holds the {role} weights {given}: the blend would replace "
                                    "them; give another folder")
    card_p, state_p = load_weights(parent)
    card_t, state_t = load_weights(tuned)
    if card_p.get("model") != card_t.get("model"):
        raise SegmentationError(f"{parent} and {tuned} hold different networks ({card_p.get('model')} vs "
                                f"{card_t.get('model')}); only weights of one network blend")
    state = {k: ((1 - alpha) * state_p[k].double() + alpha * v.double()).to(v.dtype) if v.is_floating_point() else v
             for k, v in state_t.items()}
    model = build_model(card_t, state, f"blend of {parent} and {tuned}")
    card = card_t  # loaded here, ours to change
    parent_digest = state_digest(state_p)
    card["training"]["blend"] = {"parent": str(parent), "parent_state_sha256": parent_digest,
                                 "tuned": str(tuned), "tuned_state_sha256": state_digest(state_t),
                                 "tuned_from_parent": (card_t["training"].get("init") or {}).get("state_sha256")
                                 == parent_digest, "alpha": alpha, "command": command}
    card["metrics"] = {"val": {}, "note": "blended weights: the tuned run's validation result does not apply"}
    return save_weights(model, card, out)

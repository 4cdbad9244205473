"""Generator checkpoints: a plain state dict (``<name>.pt``) plus a JSON file beside it (``<name>.json``).

The JSON file holds the format tag, the :class:`~icpbench.learning.network.GeneratorConfig` needed
to rebuild the network, and a free-form *model card* (training data, budget, loss weights, epochs,
wall time, resulting Table 1 numbers, ...; docs/architecture.md, "Training and checkpoints").
Weights are loaded with
``torch.load(path, weights_only=True)``, which refuses pickled Python objects, so opening a
checkpoint never runs code from the file. Every failure raises
:class:`~icpbench.core.errors.CheckpointError` saying which file is wrong and how.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from icpbench.core.errors import CheckpointError, InputError
from icpbench.learning.network import Generator, GeneratorConfig

FORMAT = "icpbench-generator"
FORMAT_VERSION = 1
#: State-dict entry holding the SHA-256 of the JSON's network config, written at save time: a JSON
#: edited afterwards (same tensor shapes, other behaviour) is refused. Older files lack it.
CONFIG_HASH_KEY = "_icpbench_config_sha256"


def config_hash(config: Mapping[str, Any]) -> torch.Tensor:
    """SHA-256 (32 uint8) of a generator config dict, as canonical JSON."""
    import hashlib

    blob = json.dumps(dict(config), sort_keys=True, allow_nan=False).encode()
    return torch.tensor(list(hashlib.sha256(blob).digest()), dtype=torch.uint8)


@dataclass
class LoadedGenerator:
    """A loaded checkpoint: the model (in eval mode), its config, model card and raw JSON."""

    model: Generator
    config: GeneratorConfig
    card: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)


def config_path(path: str | os.PathLike[str]) -> Path:
    """The JSON file that belongs to the weights file ``path`` (same name, ``.json`` suffix)."""
    p = Path(path)
    if p.suffix == ".json":
        raise InputError(f"{p} is the JSON config; pass the weights file (e.g. {p.with_suffix('.pt')})")
    return p.with_suffix(".json")


def _atomic_write(path: Path, write: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def save_checkpoint(model: Generator, path: str | os.PathLike[str],
                    card: Mapping[str, Any] | None = None) -> Path:
    """Write ``model``'s state dict to ``path`` (e.g. ``gen.pt``) and its config + ``card`` to
    ``gen.json``. Both files are written atomically (temporary file + rename).

    Returns:
        The weights path.

    Raises:
        InputError: ``card`` is not JSON-serialisable, or ``path`` names the JSON file.
    """
    p = Path(path)
    json_path = config_path(p)
    from icpbench import __version__

    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": model.config.to_dict(),
        "card": dict(card or {}),
        "num_parameters": model.num_parameters(),
        "icpbench_version": __version__,
        "torch_version": torch.__version__,
    }
    try:
        text = json.dumps(meta, indent=2, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise InputError(f"the model card must be JSON-serialisable (str, numbers, lists, dicts): {e}") from e
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    state[CONFIG_HASH_KEY] = config_hash(meta["config"])
    p.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(p, lambda t: torch.save(state, t))
    _atomic_write(json_path, lambda t: t.write_text(text + "\n", encoding="utf-8"))
    return p


def read_checkpoint_meta(path: str | os.PathLike[str]) -> tuple[GeneratorConfig, dict[str, Any]]:
    """Read and validate the JSON beside the weights file ``path`` without loading weights.

    Returns:
        (config, meta) where ``meta["card"]`` is the model card.
    """
    json_path = config_path(path)
    if not json_path.is_file():
        raise CheckpointError(
            f"config file {json_path} is missing; a generator checkpoint is a state dict "
            f"({Path(path).name}) plus the JSON config beside it, both written by save_checkpoint")
    try:
        meta = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"config file {json_path} is not valid JSON: {e}") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"config file {json_path} is not an icpbench generator config "
                              f"(expected \"format\": \"{FORMAT}\")")
    version = meta.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise CheckpointError(f"config file {json_path} has format_version {version!r}; this icpbench "
                              f"reads version <= {FORMAT_VERSION} (upgrade icpbench)")
    try:
        cfg = GeneratorConfig.from_dict(meta.get("config"))
    except InputError as e:
        raise CheckpointError(f"config file {json_path} has an invalid generator config: {e}") from e
    if not isinstance(meta.get("card", {}), dict):
        raise CheckpointError(f"config file {json_path}: \"card\" must be a JSON object")
    meta.setdefault("card", {})
    return cfg, meta


def _refusal_reason(msg: str) -> str:
    m = re.search(r"WeightsUnpickler error:\s*(.+?)(?: was not an allowed global|\n\n|$)", msg, re.S)
    return m.group(1).strip() if m else msg.splitlines()[0]


def _no_unsafe_advice(text: str) -> str:
    """``text`` without torch's sentences that advise loading with ``weights_only=False``."""
    parts = re.split(r"(?<=[.!?])\s+|\n+", text)
    return " ".join(p for p in parts if "weights_only" not in p or "=True" in p).strip()


def check_device(device: str | torch.device) -> None:
    """Raise :class:`CheckpointError` when ``device`` names an accelerator this machine lacks
    (checked before loading, so that the failure is not reported as a corrupt file)."""
    kind = torch.device(device).type
    if kind == "cuda" and not torch.cuda.is_available():
        raise CheckpointError(f"device {str(device)!r} was asked for, but CUDA is not available on "
                              "this machine; use device=cpu (e.g. --attack-param "
                              "generator.device=cpu)")
    if kind == "mps" and not torch.backends.mps.is_available():
        raise CheckpointError(f"device {str(device)!r} was asked for, but MPS is not available on "
                              "this machine; use device=cpu")


def _load_state(path: Path, map_location: str | torch.device) -> dict[str, torch.Tensor]:
    check_device(map_location)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        if "Weights only load failed" in str(e) and "Unsupported global" in str(e):
            raise CheckpointError(
                f"{path} holds Python objects that safe loading (torch.load weights_only=True) refuses "
                f"({_refusal_reason(str(e))}); a generator checkpoint must be a plain state dict "
                "written by save_checkpoint. Do not load it unsafely unless you trust its source."
            ) from e
        raise CheckpointError(
            f"{path} is refused by safe loading (torch.load weights_only=True stopped: "
            f"{_no_unsafe_advice(_refusal_reason(str(e)))}): it is corrupt or not a file written "
            "by torch.save; it may be a pickle that carries code. Do not load it unsafely unless "
            "you trust its source.") from e
    except Exception as e:  # torch raises OSError, EOFError, RuntimeError, KeyError, ... on bad bytes
        raise CheckpointError(
            f"{path} is truncated or corrupt and cannot be read by torch.load "
            f"({type(e).__name__}: {_no_unsafe_advice(str(e))}); re-download or re-save it") from e
    if not isinstance(state, dict) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise CheckpointError(f"{path} does not contain a state dict (a dict of name -> tensor), "
                              f"got {type(state).__name__}")
    return state


def check_state_dict(model: torch.nn.Module, state: Mapping[str, torch.Tensor], where: str = "") -> None:
    """Raise :class:`CheckpointError` naming the first missing, unexpected or mis-shaped key."""
    expected = model.state_dict()
    src = f" in {where}" if where else ""
    missing = [k for k in expected if k not in state]
    if missing:
        raise CheckpointError(
            f"state dict{src} lacks {len(missing)} parameter(s) of this architecture, first "
            f"{missing[0]!r}: it was saved from a different architecture or config")
    unexpected = [k for k in state if k not in expected]
    if unexpected:
        raise CheckpointError(
            f"state dict{src} has {len(unexpected)} unexpected key(s), first {unexpected[0]!r}: "
            "it was saved from a different architecture or config")
    for k, v in expected.items():
        if tuple(state[k].shape) != tuple(v.shape):
            raise CheckpointError(
                f"state dict{src}: {k!r} has shape {tuple(state[k].shape)}, this config needs "
                f"{tuple(v.shape)} (different architecture or config, e.g. conditioned on/off)")


def load_checkpoint(path: str | os.PathLike[str],
                    map_location: str | torch.device = "cpu") -> LoadedGenerator:
    """Rebuild a :class:`Generator` from ``path`` (weights) and the JSON beside it; eval mode.

    Raises:
        CheckpointError: missing/corrupt weights, missing/invalid JSON config, a state dict that
            does not match the config, or a file that ``weights_only`` loading refuses.
    """
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(f"generator checkpoint not found: {p}")
    cfg, meta = read_checkpoint_meta(p)
    state = _load_state(p, map_location)
    stored = state.pop(CONFIG_HASH_KEY, None)
    model = Generator(cfg)
    check_state_dict(model, state, str(p))
    if stored is not None and not torch.equal(stored.cpu(), config_hash(meta["config"])):
        raise CheckpointError(f"{config_path(p)} was edited after {p.name} was saved (its network "
                              "config no longer matches the hash stored with the weights); restore "
                              "it or re-save the checkpoint with save_checkpoint")
    model.load_state_dict(state)
    model.to(map_location).eval()
    return LoadedGenerator(model=model, config=cfg, card=meta["card"], meta=meta)

"""Q-network checkpoints: weights plus plain-python metadata, loaded with ``weights_only=True``.

Two kinds of file share one layout (a dict with ``meta`` and ``weights``):

- a *model* checkpoint (``data/qnet.pt``, what the RL swarms load): weights and metadata only;
- a *training state* (``<out>/state.pt``, what ``twin pretrain`` resumes from): the same plus
  the target network, the optimizer, the RNG states, the epoch and the replay data's seed.

Both are written atomically (temporary file in the same folder, fsync, ``os.replace``), so a
run killed at any moment leaves either the previous file or the new one, never half of one.
Anything wrong with a file reaches the user as one :class:`~twin.errors.UserError` line.
"""

from __future__ import annotations

import itertools
import re
import warnings
from pathlib import Path
from typing import Any

import torch

from twin import __version__
from twin.errors import UserError
from twin.files import atomic_write, not_a_file
from twin.grid import ACTIONS
from twin.states import DEFAULT_STATE, STATE_VARIANTS, StateVariant

FORMAT = "twin-qnet"
FORMAT_VERSION = 1


def model_metadata(
    layers,
    config: dict[str, Any],
    seed: int,
    epoch: int,
    state: str = DEFAULT_STATE,
    history: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The metadata every checkpoint carries (plain python types only); ``state`` names the
    state variant (:mod:`twin.states`) the network reads; ``history`` (a state that reads the
    nowcast): how its training history was made (generator, days, seeds)."""
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "layers": [int(n) for n in layers],
        "actions": list(ACTIONS),
        "state": state,
        "state_layout": list(STATE_VARIANTS[state].layout),
        "config": config,
        "seed": int(seed),
        "epoch": int(epoch),
        "twin_version": __version__,
        "torch_version": str(torch.__version__),
    }
    if history is not None:
        meta["history"] = history
    return meta


def atomic_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` to a temporary file beside ``path``, then renamed into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def save_model(path: str | Path, weights: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    """Write a model checkpoint (weights + metadata)."""
    atomic_save({"meta": meta, "weights": {k: v.detach().cpu() for k, v in weights.items()}}, path)


def read_checkpoint(path: str | Path, hint: str | None = None) -> dict[str, Any]:
    """Load and check a checkpoint file; every failure is a one-line :class:`UserError` ending
    in ``hint`` (the fix; by default, re-create it or point to another)."""
    path = Path(path)
    hint = hint or "re-create it with `twin pretrain` or point to another checkpoint"
    why = not_a_file(path)
    if why is not None:
        raise UserError(f"checkpoint {path} {why}; {hint}")
    try:
        with warnings.catch_warnings():  # the one-line error below says it all
            warnings.simplefilter("ignore")
            blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for truncated/corrupt/unsafe files
        text = str(exc)  # torch's weights-only refusal: its advice to load unsafely, in colour
        if re.search(r"Unsupported global: GLOBAL \w", text):  # a class or function, by name
            raise UserError(
                f"checkpoint {path} holds Python objects beyond tensors (a whole module saved "
                f"with torch.save(model), say), which twin does not unpickle; {hint}"
            ) from None
        if "Weights only load failed" in text:
            text = text.partition("WeightsUnpickler error:")[2].strip() or "no tensors"
        first = text.strip().splitlines()[0] if text.strip() else ""
        first = re.sub(r"\x1b\[[0-9;]*m", "", first)  # no terminal colours in the one line
        first = first if len(first) <= 120 else first[:120].rsplit(" ", 1)[0] + " ..."
        raise UserError(
            f"checkpoint {path} is corrupt or not a torch file ({type(exc).__name__}: {first}); "
            f"{hint}"
        ) from None
    if (
        not isinstance(blob, dict)
        or not isinstance(blob.get("meta"), dict)
        or not isinstance(blob.get("weights"), dict)
    ):
        raise UserError(f"checkpoint {path} is not a twin Q-network checkpoint; {hint}")
    meta = blob["meta"]
    if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise UserError(
            f"checkpoint {path} has format {meta.get('format')!r} v{meta.get('format_version')}, "
            f"expected {FORMAT!r} v{FORMAT_VERSION}; {hint}"
        )
    if list(meta.get("actions", [])) != list(ACTIONS):
        raise UserError(
            f"checkpoint {path} uses action order {meta.get('actions')}, this version "
            f"{list(ACTIONS)}; {hint}"
        )
    for key in ("seed", "epoch"):
        value = meta.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise UserError(
                f"checkpoint {path}: meta.{key} = {str(value)[:40]} is not a whole number >= 0; "
                f"{hint}"
            )
    variant = checkpoint_state(path, meta)
    if list(meta.get("state_layout", [])) != list(variant.layout):
        raise UserError(
            f"checkpoint {path} was trained on another layout of state {variant.name!r}; {hint}"
        )
    for part in ("weights", "target"):
        for name, value in (blob.get(part) or {}).items():
            if isinstance(value, torch.Tensor) and (
                not value.is_floating_point() or value.layout != torch.strided
            ):  # twin writes dense float tensors: integer weights are truncated ones
                kind = str(value.dtype) if value.layout == torch.strided else str(value.layout)
                raise UserError(
                    f"checkpoint {path}: {part} {name!r} are {kind.replace('torch.', '')}, not "
                    f"the dense floating-point tensors twin writes; {hint}"
                )
            if isinstance(value, torch.Tensor) and not bool(torch.isfinite(value).all()):
                raise UserError(
                    f"checkpoint {path}: {part} {name!r} holds non-finite values (NaN or inf: "
                    f"a diverged training); {hint}"
                )
    return blob


def check_recorded_checkpoints(path: Path, policies: dict[str, Any]) -> None:
    """run.json's (``path``) records of learned swarms (``policies``) against their checkpoint,
    where it is still at the recorded path with the recorded sha256: its epochs and layers
    are the checkpoint's own, not edited since (a checkpoint gone or changed is not read)."""
    from twin.files import file_sha256
    from twin.readback import RERUN

    for swarm, policy in policies.items():
        if not isinstance(policy, dict) or not isinstance(policy.get("checkpoint"), str):
            continue
        checkpoint = Path(policy["checkpoint"])
        try:
            same = checkpoint.is_file() and file_sha256(checkpoint) == policy.get("sha256")
        except OSError:
            continue
        if not same:
            continue
        try:
            meta = read_checkpoint(checkpoint)["meta"]
        except UserError:
            continue
        for key, own in (("trained_epochs", meta.get("epoch")), ("layers", meta.get("layers"))):
            if key in policy and policy[key] != own:
                raise UserError(
                    f"{path}: policies.{swarm}.{key} = {str(policy[key])[:40]}, but its checkpoint "
                    f"{checkpoint} (the recorded sha256) has {str(own)[:40]}; {RERUN}"
                )


def checkpoint_state(path: str | Path, meta: dict[str, Any]) -> StateVariant:
    """The state variant a checkpoint's network reads: ``meta["state"]``, ``"paper"`` for a
    checkpoint written before variants existed; an unknown one is refused in one line."""
    name = meta.get("state", DEFAULT_STATE)
    if not isinstance(name, str) or name not in STATE_VARIANTS:
        known = ", ".join(repr(n) for n in STATE_VARIANTS)
        raise UserError(
            f"checkpoint {path}: state variant {str(name)[:40]!r} is not one this version "
            f"builds ({known}); re-create it with `twin pretrain`"
        )
    return STATE_VARIANTS[name]


def load_qnet(path: str | Path):
    """The :class:`~twin.learning.qnet.QNetwork` stored in ``path`` (eval mode) and its metadata."""
    from twin.learning.qnet import QNetwork

    blob = read_checkpoint(path)
    meta = blob["meta"]
    layers = meta.get("layers")
    if (
        not isinstance(layers, (list, tuple))
        or len(layers) < 2
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in layers)
    ):
        raise UserError(
            f"checkpoint {path}: meta.layers = {str(layers)[:60]} is not a list of layer "
            "widths (whole numbers >= 1); re-create it with `twin pretrain`"
        )
    variant = checkpoint_state(path, meta)
    if layers[0] != variant.size:
        raise UserError(
            f"checkpoint {path}: its first layer takes {layers[0]} values but its state "
            f"variant {variant.name!r} has {variant.size}; re-create it with `twin pretrain`"
        )
    # the layers' parameters are counted before any is allocated: a meta.layers far larger
    # than the stored weights is refused here, not after asking for gigabytes
    wanted = sum(a * b + b for a, b in itertools.pairwise(layers))
    stored = sum(v.numel() for v in blob["weights"].values() if isinstance(v, torch.Tensor))
    if wanted != stored:
        raise UserError(
            f"checkpoint {path}: weights do not match meta.layers = {str(layers)[:60]} (it "
            f"needs {wanted:,} weights, the file holds {stored:,}); re-create it with `twin "
            "pretrain`"
        )
    try:
        net = QNetwork(meta["layers"])
        net.load_state_dict(blob["weights"])
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        first = str(exc).strip().splitlines()[0][:120] if str(exc).strip() else ""
        raise UserError(
            f"checkpoint {path}: weights do not match layers {meta.get('layers')} "
            f"({type(exc).__name__}: {first}); re-create it with `twin pretrain`"
        ) from None
    net.eval()
    _check_finite_q(net, variant.size, path)
    return net, meta


def _check_finite_q(net, size: int, path) -> None:
    """The network's Q-values are finite on states in [0, 1] (eq. (s)'s values) and tell the
    actions apart: weights that are finite but huge overflow to inf or NaN, and the argmax then
    picks no action at all."""
    generator = torch.Generator().manual_seed(0)
    states = torch.cat([torch.zeros(1, size), torch.ones(1, size),
                        torch.rand(62, size, generator=generator)])  # fmt: skip
    with torch.no_grad():
        q = net(states)
    if not bool(torch.isfinite(q).all()):
        with torch.no_grad():
            biggest = max(float(p.abs().max()) for p in net.parameters())
        raise UserError(
            f"checkpoint {path}: its Q-values overflow to inf or NaN on states in [0, 1] "
            f"(weights up to {biggest:.3g}: a diverged training); re-create it with `twin "
            "pretrain` or point to another checkpoint"
        )
    if not bool((q != q[:, :1]).any()):
        # finite Q-values can still be useless: an output bias of 1e30 swallows every
        # difference in float32, and the argmax then always picks the first action
        raise UserError(
            f"checkpoint {path}: its Q-values are equal for every action on every probe state "
            f"(Q = {float(q[0, 0]):.3g}: the network cannot choose a move); re-create it with "
            "`twin pretrain` or point to another checkpoint"
        )


def default_checkpoint() -> Path:
    """The shipped, pretrained checkpoint ``data/qnet.pt`` (:mod:`twin.resources`)."""
    from twin.resources import shipped_checkpoint

    return shipped_checkpoint()

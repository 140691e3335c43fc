"""Checkpoint files: what the trainer saves and what the trainer and the evaluator read.

One ``checkpoint.pt`` holds the run's config, the networks, the optimiser,
the value normaliser and the RNG states (so ``--resume`` continues exactly).
The evaluator needs only the actor and the config (:func:`load_actor`), so
it reads checkpoints through this module and never imports the trainer.

Checkpoints travel (README invites copying other people's ``runs/``), so a
checkpoint is data, never code: it is read with ``torch.load(...,
weights_only=True)``, which unpickles tensors and plain Python values only,
and every part is then checked for its type and shape (:func:`validate_payload`)
so that a damaged or hostile file is one :class:`CheckpointError` line.
Format 2 stores the RNG states as tensors and ints for that reason; format-1
files (pickled numpy RNG state) are refused with the command that converts
them (:func:`convert_checkpoint`, ``diacc convert-checkpoint``).
"""

from __future__ import annotations

import math
import pickle
import random
import warnings
import zipfile
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from diacc.config import CONFIG_SCHEMA, TrainConfig, stored_config
from diacc.envs.observation import ObservationSpec
from diacc.errors import DiaccError
from diacc.fileio import atomic_target
from diacc.learn.agent import Agent
from diacc.learn.models.registry import build_networks


class CheckpointError(DiaccError, RuntimeError):
    """A checkpoint is missing, corrupt, or belongs to another run layout."""


#: Version of the checkpoint layout: 2 stores the RNG states as tensors and ints.
FORMAT = 2


def save_checkpoint(
    path: Path, agent: Agent, cfg: TrainConfig, update: int, global_step: int
) -> None:
    """Write everything ``--resume`` needs, atomically (a killed run keeps the last file)."""
    payload = {
        "format": FORMAT,
        "config": asdict(cfg),
        "config_schema": CONFIG_SCHEMA,
        "variant": cfg.variant,
        "obs_spec": asdict(ObservationSpec.from_config(cfg.env.obs)),
        "update": update,
        "global_step": global_step,
        "actor": agent.actor.state_dict(),
        "critic": agent.critic.state_dict(),
        "value_norm": agent.value_norm.state_dict(),
        "optimizer": agent.optimizer.state_dict(),
        "rng": rng_state(),
    }
    try:
        with atomic_target(path) as tmp:
            try:
                torch.save(payload, tmp)
            except RuntimeError:  # torch's zip writer (EFBIG, EIO): "enforce fail at ..."
                raise OSError("torch could not write it: disk full or file too large") from None
    except OSError as exc:  # disk full, read-only directory: the old checkpoint stays
        reason = getattr(exc, "reason", None) or exc.strerror or str(exc) or type(exc).__name__
        raise CheckpointError(
            f"cannot write checkpoint {path} ({reason}); the previous checkpoint is unchanged"
        ) from None


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict:
    """Read and check a checkpoint; raise :class:`CheckpointError` (one line) if it is unusable.

    ``weights_only=True``: unpickling builds tensors and plain values only, so
    a hostile file cannot run code here.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    _check_archive(path)
    try:
        with warnings.catch_warnings():  # torch warns of odd pickle protocols: the error says it
            warnings.simplefilter("ignore", UserWarning)
            payload = torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as exc:
        if "numpy" in str(exc) and _looks_like_format_1(path):
            raise CheckpointError(
                f"checkpoint {path} is in the old format 1 (numpy RNG state); convert it "
                f"once with: diacc convert-checkpoint {path}"
            ) from None
        raise CheckpointError(
            f"checkpoint {path} holds objects other than tensors and plain values "
            "(refused: loading it could run code)"
        ) from None
    except Exception as exc:  # noqa: BLE001 - any other failure means truncated or garbled
        raise CheckpointError(f"checkpoint {path} is corrupt ({type(exc).__name__})") from None
    validate_payload(payload, path)
    return payload


def _check_archive(path: Path) -> None:
    """Refuse a zip checkpoint whose entries unpack to more than the file holds.

    ``torch.save`` stores every entry uncompressed; a compressed entry can
    unpack to a thousand times its size (a 1 MB file once took 1.25 GB before
    it was refused), so one is refused before anything is unpacked.
    """
    if not zipfile.is_zipfile(path):
        return  # torch's legacy format, or not a checkpoint (torch.load says which)
    try:
        with zipfile.ZipFile(path) as archive:
            entries = archive.infolist()
    except (zipfile.BadZipFile, OSError, ValueError):
        raise CheckpointError(f"checkpoint {path} is corrupt (BadZipFile)") from None
    unpacked = sum(entry.file_size for entry in entries)
    if (
        any(entry.compress_type != zipfile.ZIP_STORED for entry in entries)
        or unpacked > path.stat().st_size
    ):
        raise CheckpointError(
            f"checkpoint {path} holds compressed entries ({unpacked} bytes unpacked from "
            f"{path.stat().st_size}); torch.save writes none, so it is refused"
        )


def _looks_like_format_1(path: Path) -> bool:
    """Whether the file's only non-tensor objects are numpy arrays (an old diacc checkpoint)."""
    try:
        unsafe = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # noqa: BLE001 - unreadable: not an old checkpoint
        return False
    return bool(unsafe) and set(unsafe) <= _NUMPY_ARRAY_GLOBALS


#: What a numpy array needs to be unpickled, as torch names the globals.
_NUMPY_ARRAY_GLOBALS = {f"numpy.{core}.multiarray._reconstruct" for core in ("core", "_core")} | {
    "numpy.ndarray",
    "numpy.dtype",
    "numpy.dtypes.UInt32DType",
}


def validate_payload(payload: object, path: Path) -> None:
    """One-line :class:`CheckpointError` unless ``payload`` has a format-2 checkpoint's structure.

    Checks types and shapes, not values the training code re-checks (the
    config goes through :func:`config_from_checkpoint`, the networks through
    ``load_state_dict``), so that nothing later fails with a KeyError or
    a TypeError traceback on a damaged file.
    """

    def bad(what: str) -> CheckpointError:
        return CheckpointError(f"checkpoint {path} is damaged: {what}")

    if not isinstance(payload, dict) or "format" not in payload:
        raise CheckpointError(f"checkpoint {path} is not a diacc checkpoint")
    if payload["format"] != FORMAT:
        raise CheckpointError(
            f"checkpoint {path} has format {payload['format']!r}; this diacc reads format {FORMAT}"
        )
    types = {
        "config": dict, "variant": str, "obs_spec": dict, "update": int, "global_step": int,
        "actor": dict, "critic": dict, "value_norm": dict, "optimizer": dict, "rng": dict,
    }  # fmt: skip
    for key, kind in types.items():
        if key not in payload:
            raise bad(f"no {key!r}")
        if not isinstance(payload[key], kind) or isinstance(payload[key], bool):
            raise bad(f"{key!r} is a {type(payload[key]).__name__}, not a {kind.__name__}")
    if payload["update"] < 0 or payload["global_step"] < 0:
        raise bad("negative update or global_step")
    if not all(isinstance(v, int) for v in payload["obs_spec"].values()):
        raise bad("'obs_spec' holds a value that is not an integer")
    for part in ("actor", "critic", "value_norm"):
        for name, tensor in payload[part].items():
            if not isinstance(tensor, torch.Tensor):
                raise bad(f"{part}.{name} is not a tensor")
            if torch.is_floating_point(tensor) and not torch.isfinite(tensor).all():
                raise CheckpointError(f"checkpoint {path} has NaN/inf in {part}.{name}")
    if not {"state", "param_groups"} <= payload["optimizer"].keys():
        raise bad("'optimizer' is not an optimiser state")
    try:
        _check_rng(payload["rng"])
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f"'rng' ({exc})") from None
    try:
        config_from_checkpoint(payload)
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {path} has an unusable config ({exc})") from None


def _check_rng(rng: dict) -> None:
    """Raise KeyError/TypeError/ValueError unless ``rng`` is what :func:`rng_state` returns."""
    python, numpy_ = rng["python"], rng["numpy"]
    if not isinstance(python["version"], int) or not isinstance(python["state"], torch.Tensor):
        raise TypeError("python state")
    if python["state"].shape != (625,) or not isinstance(python["gauss"], (float, type(None))):
        raise ValueError("python state shape")
    if not isinstance(numpy_["key"], torch.Tensor) or numpy_["key"].shape != (624,):
        raise ValueError("numpy key")
    if not all(isinstance(numpy_[k], int) for k in ("pos", "has_gauss")):
        raise TypeError("numpy position")
    if not isinstance(numpy_["cached_gaussian"], float):
        raise TypeError("numpy cached gaussian")
    if not isinstance(rng["torch"], torch.Tensor) or rng["torch"].dtype != torch.uint8:
        raise TypeError("torch state")
    cuda = rng["cuda"]
    if cuda is not None and not all(isinstance(t, torch.Tensor) for t in cuda):
        raise TypeError("cuda states")
    key = numpy_["key"]
    if key.dtype != torch.int64 or not bool(((key >= 0) & (key < 2**32)).all()):
        raise ValueError("numpy key holds values outside 32 bits")
    # Restore each state into a throwaway generator: what set_rng_state would refuse
    # (a torch state of another size, a Python position past 624) is refused here.
    try:
        random.Random().setstate(
            (python["version"], tuple(python["state"].tolist()), python["gauss"])
        )
        np.random.RandomState().set_state(
            ("MT19937", key.numpy().astype(np.uint32), numpy_["pos"], numpy_["has_gauss"],
             numpy_["cached_gaussian"])
        )  # fmt: skip
        torch.Generator().set_state(rng["torch"])
    except (OverflowError, RuntimeError) as exc:
        raise ValueError(str(exc).splitlines()[0]) from None


def restore(agent: Agent, payload: dict, cfg: TrainConfig, path: Path) -> None:
    """Load a checkpoint's state into ``agent`` after checking it fits ``cfg``."""
    _load_networks(agent, payload, cfg, path)
    try:
        _check_optimizer(payload["optimizer"], agent.optimizer)
        agent.optimizer.load_state_dict(payload["optimizer"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CheckpointError(
            f"checkpoint {path} has a damaged optimiser state ({message})"
        ) from None


#: Per-parameter Adam tensors, each of its parameter's shape.
_MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")


def _check_optimizer(saved: dict, optimizer: torch.optim.Optimizer) -> None:
    """ValueError/TypeError unless ``saved`` is a state of ``optimizer``'s groups and shapes.

    ``load_state_dict`` checks group and parameter counts but not the moments'
    shapes, which would fail in the first update after the resume.
    """
    groups, state = saved["param_groups"], saved["state"]
    if not isinstance(groups, list) or len(groups) != len(optimizer.param_groups):
        raise ValueError(f"{len(groups)} parameter groups, not {len(optimizer.param_groups)}")
    ids = {}
    for number, (group, own) in enumerate(zip(groups, optimizer.param_groups, strict=True)):
        if not isinstance(group, dict) or not isinstance(group.get("params"), list):
            raise TypeError(f"parameter group {number} is not a group")
        if len(group["params"]) != len(own["params"]):
            raise ValueError(
                f"parameter group {number} has {len(group['params'])} parameters, "
                f"not {len(own['params'])}"
            )
        for key in ("lr", "eps", "weight_decay"):
            if not isinstance(group.get(key), (int, float)) or not math.isfinite(group[key]):
                raise ValueError(f"parameter group {number} has no finite {key!r}")
        ids.update(zip(group["params"], own["params"], strict=True))
    if not isinstance(state, dict) or not set(state) <= set(ids):
        raise ValueError("moments of parameters that are in no group")
    for pid, moments in state.items():
        if not isinstance(moments, dict):
            raise TypeError(f"state of parameter {pid} is not a dict")
        for key in _MOMENTS:
            tensor = moments.get(key)
            if tensor is not None and (
                not isinstance(tensor, torch.Tensor) or tensor.shape != ids[pid].shape
            ):
                raise ValueError(f"{key} of parameter {pid} does not have its parameter's shape")


def _load_networks(agent: Agent, payload: dict, cfg: TrainConfig, path: Path) -> None:
    """The checkpoint's networks and value normaliser into ``agent`` (one-line errors)."""
    _check_fits(payload, cfg, path)
    try:
        agent.actor.load_state_dict(payload["actor"])
        agent.critic.load_state_dict(payload["critic"])
    except RuntimeError:
        raise CheckpointError(
            f"checkpoint {path} does not match the {cfg.variant} networks (other model.* sizes)"
        ) from None
    try:
        agent.value_norm.load_state_dict(payload["value_norm"])
    except RuntimeError:
        raise CheckpointError(
            f"checkpoint {path} has a damaged value normaliser (keys "
            f"{sorted(payload['value_norm'])}, not {sorted(agent.value_norm.state_dict())})"
        ) from None


def init_networks(agent: Agent, path: Path, cfg: TrainConfig) -> dict:
    """Start ``agent`` from the networks and value normaliser of the checkpoint at ``path``.

    Fine-tuning (``TrainConfig.init_from``): unlike :func:`restore`, the optimiser
    and the schedules start afresh, and the checkpoint may come from another
    backend, map or scenario. It must hold the same variant, observation layout
    and network sizes (one-line :class:`CheckpointError` otherwise). Returns the
    payload's provenance: variant, backend, map, update and step count.
    """
    payload = load_checkpoint(path)
    _load_networks(agent, payload, cfg, path)
    env = payload["config"].get("env", {})
    return {
        "variant": payload["variant"],
        "backend": env.get("backend"),
        "map": env.get("map"),
        "update": payload["update"],
        "global_step": payload["global_step"],
    }


def load_actor(path: Path, variant: str | None = None) -> tuple[torch.nn.Module, TrainConfig, dict]:
    """(actor in eval mode on the CPU, training config, payload) of a checkpoint.

    ``variant``, if given, must be the checkpoint's (guards against comparing
    the wrong runs).
    """
    payload = load_checkpoint(path)
    if variant is not None and payload.get("variant") != variant:
        raise CheckpointError(
            f"checkpoint {path} is for variant {payload.get('variant')!r}, not {variant!r}"
        )
    try:
        cfg = config_from_checkpoint(payload)
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {path} has an unusable config ({exc})") from None
    _check_fits(payload, cfg, path)
    actor, _ = build_networks(cfg.variant, cfg.model, ObservationSpec.from_config(cfg.env.obs))
    try:
        actor.load_state_dict(payload["actor"])
    except RuntimeError:
        raise CheckpointError(f"checkpoint {path} does not match the {cfg.variant} actor") from None
    return actor.eval(), cfg, payload


def _check_fits(payload: dict, cfg: TrainConfig, path: Path) -> None:
    """One-line :class:`CheckpointError` unless the checkpoint's networks fit ``cfg``."""
    if payload["variant"] != cfg.variant:
        raise CheckpointError(
            f"checkpoint {path} is for variant {payload['variant']!r}, not {cfg.variant!r}"
        )
    # Older checkpoints stored only K, T and N; compare what a checkpoint holds. The
    # critic's row count (max_vehicles) is a size, not a layout: the graph networks
    # take any count (fine-tuning a release agent on a demand road needs more rows),
    # and a network whose weights depend on it (the MLP critic) fails to load below.
    spec = asdict(ObservationSpec.from_config(cfg.env.obs))
    held = {key: value for key, value in payload["obs_spec"].items() if key != "max_vehicles"}
    if held != {key: spec.get(key) for key in held}:
        raise CheckpointError(f"checkpoint {path} was trained with another observation layout")


def rng_state() -> dict:
    """The Python, numpy, torch and CUDA RNG states as tensors and plain values.

    Plain types so that the checkpoint loads with ``weights_only=True``
    (numpy's own state tuple holds an ndarray, which would need unpickling code).
    """
    version, words, gauss = random.getstate()
    _, key, pos, has_gauss, cached = np.random.get_state()
    return {
        "python": {
            "version": version,
            "state": torch.tensor(words, dtype=torch.int64),
            "gauss": gauss,
        },
        "numpy": {
            "key": torch.from_numpy(key.astype(np.int64)),  # (624,) uint32 words
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached),
        },
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
    }


def set_rng_state(rng: dict) -> None:
    """Restore the RNG states saved by :func:`rng_state`."""
    python, numpy_ = rng["python"], rng["numpy"]
    random.setstate((python["version"], tuple(python["state"].tolist()), python["gauss"]))
    np.random.set_state(
        (
            "MT19937",
            numpy_["key"].numpy().astype(np.uint32),
            numpy_["pos"],
            numpy_["has_gauss"],
            numpy_["cached_gaussian"],
        )
    )
    torch.set_rng_state(rng["torch"].cpu())
    if rng["cuda"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(rng["cuda"])


def convert_checkpoint(src: Path, dst: Path | None = None) -> Path:
    """Rewrite a format-1 checkpoint (numpy RNG state) as format 2; returns the written path.

    The old file is read with ``weights_only=True`` plus numpy's array
    reconstruction as the only allowed globals, so converting runs no code
    from the file either; networks, optimiser and config are copied unchanged
    (bit-identical tensors). ``dst`` defaults to ``src`` (replaced atomically).
    """
    src, dst = Path(src), Path(dst or src)
    if not src.is_file():
        raise CheckpointError(f"checkpoint {src} does not exist")
    allowed = [np.ndarray, np.dtype, type(np.dtype(np.uint32)), _numpy_reconstruct()]
    try:
        with torch.serialization.safe_globals(allowed), warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            payload = torch.load(src, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - anything else: not an old diacc checkpoint
        raise CheckpointError(
            f"checkpoint {src} cannot be converted ({type(exc).__name__}): it holds objects "
            "other than tensors, plain values and numpy arrays"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != 1:
        raise CheckpointError(f"checkpoint {src} is not a format-1 diacc checkpoint")
    try:
        version, words, gauss = payload["rng"]["python"]
        _, key, pos, has_gauss, cached = payload["rng"]["numpy"]
        payload["rng"] = {
            "python": {
                "version": version,
                "state": torch.tensor(words, dtype=torch.int64),
                "gauss": gauss,
            },
            "numpy": {
                "key": torch.from_numpy(np.asarray(key, dtype=np.int64)),
                "pos": int(pos),
                "has_gauss": int(has_gauss),
                "cached_gaussian": float(cached),
            },
            "torch": payload["rng"]["torch"],
            "cuda": payload["rng"]["cuda"],
        }
    except (KeyError, TypeError, ValueError):
        raise CheckpointError(f"checkpoint {src} has no readable RNG state") from None
    payload["format"] = FORMAT
    validate_payload(payload, src)
    with atomic_target(dst) as tmp:
        torch.save(payload, tmp)
    return dst


def _numpy_reconstruct():
    """numpy's array-unpickling function (moved from ``numpy.core`` to ``numpy._core`` in 2.0)."""
    try:
        from numpy._core.multiarray import _reconstruct
    except ImportError:  # pragma: no cover - numpy < 2
        from numpy.core.multiarray import _reconstruct
    return _reconstruct


def config_from_checkpoint(payload: dict) -> TrainConfig:
    """Rebuild the TrainConfig stored in a checkpoint (:func:`diacc.config.stored_config`:
    migrated from its ``config_schema``, 1 when it has none, to today's)."""
    return stored_config(payload["config"], payload.get("config_schema", 1))

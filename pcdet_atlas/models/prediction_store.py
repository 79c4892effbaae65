"""A content-addressed store of a detector's predictions, shared by the models that read them.

MSF-4f, MSF-8f and PTT all take their proposals from the same CP-4f, and CP-4f is evaluated on
the same attacked frames on its own. With a :class:`PredictionStore`, whichever process runs
CP-4f on a batch first keeps its detections, and every later process that feeds CP-4f the same
batch (as a model of its own or as a two-stage model's RPN) reads them instead of running it
(docs/evaluation.md, "Sharing the RPN between models").

An entry is found by what determines the prediction, never by names: the model's class, the
arguments it was built from, every tensor of its ``state_dict`` and the plain settings of its
modules (``fold_eval``, thresholds set after the build; its *fingerprint*); this package's source
code, but for ``pcdet_atlas/evaluation`` (:func:`source_digest`); the runtime (device, its compute
capability or CPU instruction set, torch, CUDA and cuDNN versions, TF32 and deterministic-algorithm
flags, CPU thread count); and the bytes of every batch input the model reads (its
``prediction_inputs``: for CenterPoint the points with their batch column, and the batch size).
Equal keys mean equal computations, so a stored prediction is bitwise the one the model would
return: on the CPU, where torch's kernels are deterministic for a given thread count. On a GPU they
are only in deterministic mode (docs/evaluation.md); otherwise a stored prediction is one the model
may return. A model that does not declare ``prediction_inputs``, or is in training mode, cannot be
stored (error). Weights changed through ``.data`` escape the cached fingerprint (load checkpoints
with ``load_state_dict``).

Entries are files ``<root>/<model key>/<k[:2]>/<k>.pt`` written atomically, so concurrent
processes may share a root; ``<root>/<model key>/model.json`` says which model a folder holds.
An entry records its own model key and batch key (``{'model_key', 'batch_key', 'predictions'}``),
checked on every read: a file copied or moved over another entry is an error naming the file and
both keys, never served. A missing entry is a miss: predicted and stored.
"""

from __future__ import annotations

import hashlib
import json
import platform
import weakref
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from pcdet_atlas.utils.common import write_atomic

__all__ = ["PredictionStore", "model_fingerprint", "use_prediction_store"]


def _hash_tensor(h, tensor: torch.Tensor) -> None:
    """Feed a tensor's dtype, shape and bytes to the hash ``h``."""
    h.update(f"{tensor.dtype}{tuple(tensor.shape)}".encode())
    array = tensor.detach().cpu().contiguous().reshape(-1)
    h.update(memoryview(array.view(torch.uint8).numpy()) if array.numel() else b"")


# model -> (its tensors' versions and addresses, fingerprint); weak: a freed model's entry goes
_FINGERPRINTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


_SETTING_TYPES = (bool, int, float, str, type(None))


def module_settings(model: nn.Module) -> list:
    """The plain attributes (bools, numbers, strings and tuples of them) of every submodule:
    settings outside the ``state_dict`` that change what a module computes."""
    out = []
    for name, module in model.named_modules():
        for attr, value in sorted(vars(module).items()):
            if attr.startswith("_") or attr == "training":
                continue
            plain_sequence = isinstance(value, (tuple, list)) and all(
                isinstance(v, _SETTING_TYPES) for v in value
            )
            if plain_sequence:
                value = list(value)
            elif not isinstance(value, _SETTING_TYPES):
                continue
            out.append([name, attr, value])
    return out


_SOURCE_DIGEST: list[str] = []


def source_digest() -> str:
    """SHA-256 of this package's Python sources (once per process): a stored prediction is
    found only by the code that computed it. ``pcdet_atlas/evaluation`` (metrics and reports,
    which read predictions and never make them; no model imports it) is left out, so that a
    change there keeps the stored predictions."""
    if not _SOURCE_DIGEST:
        package = Path(__file__).resolve().parents[1]
        h = hashlib.sha256()
        for path in sorted(package.rglob("*.py")):
            if path.relative_to(package).parts[0] == "evaluation":
                continue
            h.update(str(path.relative_to(package)).encode())
            h.update(path.read_bytes())
        _SOURCE_DIGEST.append(h.hexdigest())
    return _SOURCE_DIGEST[0]


def runtime_key(device: torch.device) -> dict:
    """What besides the model and its inputs decides a prediction's bits on ``device``."""
    out = {
        "device": device.type, "torch": torch.__version__, "machine": platform.machine(),
        "default_dtype": str(torch.get_default_dtype()),
        "deterministic": torch.are_deterministic_algorithms_enabled(),
    }  # fmt: skip
    if device.type == "cuda":
        out.update(
            gpu=torch.cuda.get_device_name(device),
            capability=list(torch.cuda.get_device_capability(device)),
            cuda=torch.version.cuda, cudnn=torch.backends.cudnn.version(),
            tf32=[torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32],
        )  # fmt: skip
    else:
        out.update(threads=torch.get_num_threads(), cpu=torch.backends.cpu.get_cpu_capability())
    return out


def build_signature(model: nn.Module) -> dict:
    """The arguments :func:`~pcdet_atlas.models.build_network` built ``model`` from; a model
    built otherwise cannot be stored (error)."""
    signature = getattr(model, "build_signature", None)
    if signature is None:
        raise ValueError(
            f"{type(model).__name__} has no build_signature: build it with "
            "pcdet_atlas.models.build_network to store its predictions"
        )
    return signature


def model_fingerprint(model: nn.Module) -> str:
    """SHA-256 of the model's class, its :func:`build_signature`, its modules' plain settings
    (:func:`module_settings`) and its ``state_dict``. It is recomputed when a setting or a
    tensor of the state changed in place (a new checkpoint loaded)."""
    signature = build_signature(model)
    state = model.state_dict(keep_vars=True)
    settings = json.dumps(module_settings(model))
    versions = (tuple((name, t._version, t.data_ptr()) for name, t in state.items()), settings)
    cached = _FINGERPRINTS.get(model)
    if cached is not None and cached[0] == versions:
        return cached[1]
    h = hashlib.sha256()
    h.update(type(model).__qualname__.encode())
    h.update(json.dumps(signature, sort_keys=True, default=str).encode())
    h.update(settings.encode())
    for name, tensor in state.items():
        h.update(name.encode())
        _hash_tensor(h, tensor)
    digest = h.hexdigest()
    _FINGERPRINTS[model] = (versions, digest)
    return digest


class PredictionStore:
    """Predictions of frozen models under ``root``, found by their inputs (module docstring).

    ``hits`` / ``misses`` count the batches read from the store and those predicted (and
    stored); :meth:`counts` returns them.
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.hits = 0
        self.misses = 0

    def counts(self) -> dict[str, int]:
        return {"hits": self.hits, "misses": self.misses}

    def model_key(self, model: nn.Module, device: torch.device) -> str:
        """The folder of ``model``'s entries on ``device``: its fingerprint, this package's
        source and the runtime (:func:`runtime_key`)."""
        runtime = json.dumps(runtime_key(device), sort_keys=True)
        text = f"{model_fingerprint(model)}|{source_digest()}|{runtime}"
        return hashlib.sha256(text.encode()).hexdigest()[:32]

    def batch_key(self, model: nn.Module, batch_dict: Mapping) -> str:
        """The hash of the batch inputs ``model.prediction_inputs`` names, and the batch size."""
        inputs = getattr(model, "prediction_inputs", None)
        if not inputs:
            raise TypeError(
                f"{type(model).__name__} declares no prediction_inputs: its predictions cannot be "
                "stored (the store must know every batch key a prediction reads)"
            )
        h = hashlib.sha256(f"batch_size={int(batch_dict['batch_size'])}".encode())
        for key in inputs:
            if key not in batch_dict:
                raise KeyError(f"{type(model).__name__} reads batch_dict[{key!r}]; it is missing")
            value = batch_dict[key]
            h.update(key.encode())
            if isinstance(value, torch.Tensor):
                _hash_tensor(h, value)
            else:
                h.update(repr(value).encode())
        return h.hexdigest()

    @torch.no_grad()
    def predict(self, model: nn.Module, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """``model.predict(batch_dict)``, read from the store when the same model already
        predicted the same inputs there, predicted and stored otherwise."""
        if any(m.training for m in model.modules()):
            raise RuntimeError(
                f"{type(model).__name__} is in training mode: only eval-mode predictions are "
                "stored (call model.eval())"
            )
        device = next(model.parameters()).device
        model_key = self.model_key(model, device)
        folder = self.root / model_key
        key = self.batch_key(model, batch_dict)
        path = folder / key[:2] / f"{key}.pt"
        if path.is_file():
            stored = self._read(path, device, int(batch_dict["batch_size"]), (model_key, key))
            self.hits += 1
            return stored
        predictions = model.predict(batch_dict)
        self.misses += 1
        self._describe(folder, model, device)
        cpu = [{k: v.detach().cpu() for k, v in p.items()} for p in predictions]
        entry = {"model_key": model_key, "batch_key": key, "predictions": cpu}
        write_atomic(path, lambda f: torch.save(entry, f))
        return predictions

    def _read(
        self, path: Path, device: torch.device, batch_size: int, keys: tuple[str, str]
    ) -> list[dict]:
        """A stored entry, checked: the ``(model key, batch key)`` it records are ``keys``, and
        it holds one dict of tensors per sample."""
        try:
            stored = torch.load(path, map_location=device, weights_only=True)
        except Exception as err:  # noqa: BLE001 - any unreadable file gets the same message
            reason = (str(err).splitlines() or [""])[0]
            raise ValueError(
                f"prediction store entry {path} cannot be read ({type(err).__name__}: {reason}); "
                f"delete it (or the whole store, {self.root}) and run again"
            ) from err
        recorded = (
            (stored.get("model_key"), stored.get("batch_key")) if isinstance(stored, dict) else None
        )
        if recorded != keys:
            raise ValueError(
                f"prediction store entry {path} records "
                + ("no key" if recorded is None else f"the key {'/'.join(map(str, recorded))}")
                + f", but is read for {'/'.join(keys)} (model key/batch key; a file copied or "
                "moved over another?): "
                f"delete it (or the whole store, {self.root}) and run again"
            )
        stored = stored.get("predictions")
        if not (
            isinstance(stored, list) and len(stored) == batch_size
            and all(isinstance(p, dict) and all(isinstance(v, torch.Tensor) for v in p.values())
                    for p in stored)
        ):  # fmt: skip
            raise ValueError(
                f"prediction store entry {path} does not hold {batch_size} dicts of tensors; "
                f"delete it (or the whole store, {self.root}) and run again"
            )
        return stored

    def _describe(self, folder: Path, model: nn.Module, device: torch.device) -> None:
        info = folder / "model.json"
        if info.is_file():
            return
        text = json.dumps(
            {
                "model": type(model).__qualname__,
                "fingerprint": model_fingerprint(model),
                "build_signature": build_signature(model),
                "source": source_digest(),
                "runtime": runtime_key(device),
                "prediction_inputs": list(model.prediction_inputs),
            },
            indent=1, default=str,
        )  # fmt: skip
        write_atomic(info, lambda f: f.write(text.encode()))


def use_prediction_store(model: nn.Module, store: PredictionStore) -> list[str]:
    """Let ``model`` keep its predictions in ``store`` if it declares its
    ``prediction_inputs``, and a two-stage model its RPN's. Returns what uses the store
    (``'model'``, ``'rpn'``; empty for a model that cannot use it)."""
    users = []
    for name, module in (("model", model), ("rpn", getattr(model, "rpn", None))):
        if module is not None and getattr(module, "prediction_inputs", None):
            build_signature(module)  # checked now, not at the first batch
            module.prediction_store = store
            users.append(name)
    return users

"""Reading the torch files a user points at (weights, ``model.pt``, training checkpoints) as data only.

Only the zip archive that ``torch.save`` writes is accepted, and it is read with
``torch.load(..., weights_only=True)``: tensors and plain containers (dict, list, tuple, str,
numbers, None) load; any other object is refused before it is built, so nothing in the file
runs. A raw pickle is never handed to an unpickler. Every problem is a
:class:`~robustbench3d.errors.DataFormatError` naming the file, in one line.
"""

from __future__ import annotations

import hashlib
import pickle
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import nn

from robustbench3d.errors import DataFormatError

#: ``format`` of a cascade weights file (both networks, ``FPointNetCascade.save``).
CASCADE_FORMAT = "robustbench3d.fpointnet_cascade/1"

_TORCH_BOILERPLATE = ("Weights only load failed", "Please file an issue", "Check the documentation")


def one_line(exc: BaseException, limit: int = 240) -> str:
    """``Type: message`` of an exception on one line, shortened to ``limit`` characters."""
    text = " ".join(part.strip() for part in str(exc).splitlines() if part.strip())
    text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _refusal(exc: pickle.UnpicklingError) -> str:
    """What torch's data-only unpickler objected to, without its advice to disable it."""
    lines = [ln.strip() for ln in str(exc).splitlines()]
    keep = [ln.removeprefix("WeightsUnpickler error:").strip() for ln in lines
            if ln and not ln.startswith(_TORCH_BOILERPLATE)]
    keep = [ln for ln in keep if ln]
    return keep[0][:240] if keep else "an object that is not a tensor or plain data"


def _archive_problem(path: Path) -> str | None:
    """Why ``path`` is not a ``torch.save`` zip archive, None if it is one."""
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except (zipfile.BadZipFile, ValueError, EOFError, NotImplementedError):
        with open(path, "rb") as f:
            head = f.read(2)
        if head[:1] == b"\x80" and head[1:2] in (b"\x02", b"\x03", b"\x04", b"\x05"):
            return "it is a raw pickle, which is never unpickled; expected the zip archive that torch.save writes"
        return "not the zip archive that torch.save writes"
    if not any(name == "data.pkl" or name.endswith("/data.pkl") for name in names):
        return "a zip archive without the data.pkl record of torch.save"
    return None


def load_torch_data(path: str | Path, what: str) -> Any:
    """Contents of the ``torch.save`` archive ``path`` (a ``what``), read as data only."""
    path = Path(path)
    if path.is_dir():
        raise DataFormatError(path, f"is a directory, expected a {what}")
    if not path.is_file():
        raise DataFormatError(path, f"no such {what}")
    try:
        if path.stat().st_size == 0:
            raise DataFormatError(path, f"empty file, not a {what}")
        problem = _archive_problem(path)
        if problem is not None:
            raise DataFormatError(path, f"not a {what}: {problem}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return torch.load(path, map_location="cpu", weights_only=True)
    except DataFormatError:
        raise
    except OSError as exc:
        raise DataFormatError(path, f"cannot read this {what}: {exc.strerror or one_line(exc)}") from None
    except pickle.UnpicklingError as exc:
        raise DataFormatError(path, f"refusing to unpickle it: not a {what}, it holds objects other than tensors "
                                    f"and plain data ({_refusal(exc)})") from None
    except Exception as exc:
        raise DataFormatError(path, f"not a {what}: torch cannot read it ({one_line(exc)})") from None


def network_part(data: Any, path: str | Path, what: str) -> dict[str, Any]:
    """``data`` checked to be one network's ``{"config": dict, "state_dict": {name: tensor}}``."""
    if not isinstance(data, dict) or not isinstance(data.get("config"), dict) \
            or not isinstance(data.get("state_dict"), dict):
        raise DataFormatError(path, f"not a {what}: expected a 'config' dict and a 'state_dict' dict")
    for key, value in data["state_dict"].items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            raise DataFormatError(path, f"entry {key!r} is not a named tensor", field="state_dict")
    return data


def network_sha256(state_dict: dict[str, Any]) -> str:
    """sha256 of a network's weights: every tensor's name, dtype, shape and bytes, in name order
    (the same for a trainer's ``model.pt``, a cascade file or a checkpoint holding that state)."""
    h = hashlib.sha256()
    for name in sorted(state_dict):
        t = torch.as_tensor(state_dict[name]).detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def shared_reference(file: str | Path, state_dict: dict[str, Any]) -> dict[str, str]:
    """The ``shared`` entry of a cascade part whose weights are ``state_dict`` as stored in ``file``
    (a weights file of the same directory, named without a path)."""
    return {"file": Path(file).name, "state_sha256": network_sha256(state_dict)}


def cascade_part(data: Any, path: str | Path, network: str, what: str) -> dict[str, Any]:
    """One network of a cascade weights file, checked: ``{"config", "state_dict"}`` stored in the
    file, or ``{"config", "shared": {"file", "state_sha256"}}`` — the weights of ``network`` in
    another weights file of the same directory (so two shipped cascades carry one copy of a stage
    they share), which must hold them itself and hash to ``state_sha256`` (:func:`network_sha256`)."""
    path = Path(path)
    if not (isinstance(data, dict) and "shared" in data and "state_dict" not in data):
        return network_part(data, path, what)
    ref = data["shared"]
    if not isinstance(data.get("config"), dict) or not isinstance(ref, dict) \
            or not all(isinstance(ref.get(k), str) for k in ("file", "state_sha256")):
        raise DataFormatError(path, f"not a {what}: a shared {network} part needs a 'config' dict and "
                                    "'shared': {'file', 'state_sha256'}", field=network)
    if Path(ref["file"]).name != ref["file"] or ref["file"] in ("", ".", ".."):
        raise DataFormatError(path, f"shared {network} file must be a bare name in the same directory, "
                                    f"got {ref['file']!r}", field=f"{network}.shared.file")
    source = path.parent / ref["file"]
    state = stored_part(source, network)
    got = network_sha256(state["state_dict"])
    if got != ref["state_sha256"]:
        raise DataFormatError(path, f"the {network} weights in {source} hash to {got}, not the "
                                    f"state_sha256 {ref['state_sha256']} this file was packed with",
                              field=f"{network}.shared.state_sha256")
    return {"config": data["config"], "state_dict": state["state_dict"]}


def stored_part(path: str | Path, network: str) -> dict[str, Any]:
    """``network``'s part as stored in ``path`` itself (a trainer ``model.pt`` or a cascade file that
    holds these weights, not a reference to another file): what a shared part may point at."""
    what = f"{network} model.pt or cascade weights file holding its weights"
    data = load_torch_data(path, what)
    if isinstance(data, dict) and data.get("format") == CASCADE_FORMAT:
        data = data.get(network)
    return network_part(data, path, what)


def load_network_part(path: str | Path, network: str) -> dict[str, Any]:
    """``{"config", "state_dict"}`` of ``network`` ("yolo" or "fpointnet") from a trainer
    ``model.pt`` or a cascade weights file (a shared part resolved), read as data only and checked."""
    what = f"{network} model.pt or cascade weights file"
    data = load_torch_data(path, what)
    if isinstance(data, dict) and data.get("format") == CASCADE_FORMAT:
        return cascade_part(data.get(network), path, network, what)
    return network_part(data, path, what)


def build_network(make: Callable[[dict[str, Any]], nn.Module], part: dict[str, Any], origin: str | Path,
                  network: str) -> nn.Module:
    """The network ``make(config)`` with ``part``'s weights loaded; a configuration it cannot be
    built from, or weights that do not fit it, are errors naming ``origin``."""
    try:
        net = make(part["config"])
    except Exception as exc:
        raise DataFormatError(origin, f"the {network} configuration is not usable ({one_line(exc)})",
                              field="config") from None
    try:
        net.load_state_dict(part["state_dict"])
    except RuntimeError as exc:
        raise DataFormatError(origin, f"the {network} weights do not fit its configuration ({one_line(exc)})",
                              field="state_dict") from None
    return net

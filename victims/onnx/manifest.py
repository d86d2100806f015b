"""The manifest of an ONNX victim directory (``manifest.json``): layout, reading and checking.

Layout (JSON object; keys in this order)::

    format          "robustbench3d.onnx_cascade/1"
    stages          list, in pipeline order, of
                      {name, file, sha256, inputs: [{name, shape, dtype}], outputs: [...]}
                    names: detector_2d, instance_segmentation, center_regression, box_estimation;
                    file: NAME.onnx in the directory, or ../SIBLING/NAME.onnx for a graph shared
                    with a sibling victim directory (``export-onnx --share``), pinned by its sha256
    exporter        {name: "dynamo" | "legacy", opset, torch, onnx, onnxscript}
    config          {yolo: YoloConfig dict, fpointnet: FPointNetConfig dict, settings: CascadeSettings dict}
    source          {victim, kwargs} — what was exported (weight files by name and sha256)
    package_version robustbench3d version that wrote it
    reproduce       {command, byte_deterministic, note}

Shapes are fixed (no symbolic dimensions); the first dimension is the graph's batch size and the
runtime pads partial batches. Everything is float32.

Standard library only.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import read_user_text, sha256_file
from robustbench3d.victims.onnx import MANIFEST_FILE

FORMAT = "robustbench3d.onnx_cascade/1"
#: ``format`` of a PointPillars ONNX victim directory (one graph; :mod:`robustbench3d.victims.pointpillars.runtime`).
POINTPILLARS_FORMAT = "robustbench3d.onnx_pointpillars/1"
DETECTOR_2D = "detector_2d"
SEGMENTATION = "instance_segmentation"
CENTER = "center_regression"
BOX = "box_estimation"
#: Stage names in pipeline order.
STAGES: tuple[str, ...] = (DETECTOR_2D, SEGMENTATION, CENTER, BOX)
#: Input and output tensor names of the three F-PN stages.
FPN_IO: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    SEGMENTATION: (("points", "one_hot"), ("seg_logits",)),
    CENTER: (("object_points", "one_hot"), ("center_delta",)),
    BOX: (("object_points", "one_hot"), ("box_output",)),
}
#: Box-net outputs: centre (3) + heading scores and residuals (2·12) + size scores (8) and residuals (3·8).
BOX_OUTPUTS = 59
#: Input name of the 2D detector; its outputs are ``head_0``, ``head_1``, ... (raw head tensors).
IMAGE_INPUT = "image"
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_NUMBER = r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?"
_NUMBER_LIST = re.compile(rf"\[\s*((?:{_NUMBER},\s*)*{_NUMBER})\s*\]")


def head_name(index: int) -> str:
    """Output name of the 2D detector's ``index``-th head."""
    return f"head_{index}"


@dataclass(frozen=True)
class TensorSpec:
    """A graph input or output: name, fixed shape, element type."""

    name: str
    shape: tuple[int, ...]
    dtype: str = "float32"

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "shape": list(self.shape), "dtype": self.dtype}

    @classmethod
    def from_dict(cls, data: Any, where: str, path: Path) -> TensorSpec:
        if not isinstance(data, dict) or not isinstance(data.get("name"), str):
            raise DataFormatError(path, f"{where}: expected {{name, shape, dtype}}, got {data!r}")
        shape = data.get("shape")
        if not isinstance(shape, list) or not all(isinstance(d, int) and not isinstance(d, bool) and d > 0
                                                  for d in shape):
            raise DataFormatError(path, f"{where} {data['name']!r}: shape must be a list of positive integers, "
                                        f"got {shape!r}")
        if data.get("dtype", "float32") != "float32":
            raise DataFormatError(path, f"{where} {data['name']!r}: dtype must be float32, got {data.get('dtype')!r}")
        return cls(data["name"], tuple(shape))


@dataclass(frozen=True)
class StageSpec:
    """One stage graph: its file (relative to the directory; see :func:`is_stage_file_name`), sha256,
    inputs and outputs."""

    name: str
    file: str
    sha256: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]

    @property
    def batch_size(self) -> int:
        """The graph's fixed batch size (first dimension of its inputs)."""
        return self.inputs[0].shape[0]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "file": self.file, "sha256": self.sha256,
                "inputs": [t.to_dict() for t in self.inputs], "outputs": [t.to_dict() for t in self.outputs]}


@dataclass(frozen=True)
class Manifest:
    """A parsed ``manifest.json`` (see the module docstring)."""

    stages: tuple[StageSpec, ...]
    exporter: dict[str, Any]
    config: dict[str, Any]
    source: dict[str, Any]
    package_version: str
    reproduce: dict[str, Any]

    def stage(self, name: str) -> StageSpec:
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "stages": [s.to_dict() for s in self.stages], "exporter": self.exporter,
                "config": self.config, "source": self.source, "package_version": self.package_version,
                "reproduce": self.reproduce}

    def to_json(self) -> str:
        """Canonical text (2-space indent, fixed key order, lists of numbers on one line, trailing newline)."""
        text = json.dumps(self.to_dict(), indent=2, allow_nan=False)
        return _NUMBER_LIST.sub(lambda m: "[" + ", ".join(m.group(1).replace(",", " ").split()) + "]", text) + "\n"


def _require(data: dict[str, Any], key: str, kind: type, path: Path, where: str = "manifest") -> Any:
    if key not in data:
        raise DataFormatError(path, f"{where}: missing key {key!r}")
    if not isinstance(data[key], kind) or (isinstance(data[key], bool) and kind is not bool):
        raise DataFormatError(path, f"{where}: {key!r} must be a {kind.__name__}, got {type(data[key]).__name__}")
    return data[key]


def is_stage_file_name(file: str) -> bool:
    """A stage ``file`` is a bare ``NAME.onnx`` in the victim directory, or ``../SIBLING/NAME.onnx``: a
    stage graph shared with the victim directory SIBLING beside it (both bare names)."""
    parts = file.split("/")
    if len(parts) == 3 and parts[0] == "..":
        parts = parts[1:]
    elif len(parts) != 1:
        return False
    return file.endswith(".onnx") and all(p not in ("", ".", "..") and "\\" not in p for p in parts)


def _stage(data: Any, index: int, path: Path) -> StageSpec:
    if not isinstance(data, dict):
        raise DataFormatError(path, f"stages[{index}] must be an object")
    where = f"stage {data.get('name', index)!r}"
    name = _require(data, "name", str, path, where)
    file = _require(data, "file", str, path, where)
    if not is_stage_file_name(file):
        raise DataFormatError(path, f"{where}: file must be a bare '*.onnx' name in the directory, or "
                                    f"'../SIBLING/NAME.onnx' for a stage shared with a sibling directory, got {file!r}")
    sha = _require(data, "sha256", str, path, where)
    if not _SHA256.match(sha):
        raise DataFormatError(path, f"{where}: sha256 must be 64 lowercase hex digits, got {sha!r}")
    ins = _require(data, "inputs", list, path, where)
    outs = _require(data, "outputs", list, path, where)
    if not ins or not outs:
        raise DataFormatError(path, f"{where}: needs at least one input and one output")
    return StageSpec(name, file, sha, tuple(TensorSpec.from_dict(t, f"{where} input", path) for t in ins),
                     tuple(TensorSpec.from_dict(t, f"{where} output", path) for t in outs))


def stage_spec(data: Any, where: str, path: Path) -> StageSpec:
    """One ``{name, file, sha256, inputs, outputs}`` graph entry of a manifest, checked (``where`` names it)."""
    return _stage(data, where, path)  # type: ignore[arg-type]


def manifest_format(directory: str | Path) -> str | None:
    """The ``format`` of the directory's ``manifest.json`` (None if unreadable or absent): which kind of ONNX
    victim the directory holds."""
    try:
        data = json.loads(read_user_text(Path(directory) / MANIFEST_FILE))
    except (OSError, ValueError, DataFormatError):
        return None
    return data.get("format") if isinstance(data, dict) and isinstance(data.get("format"), str) else None


def parse_manifest(text: str, path: Path) -> Manifest:
    """Parse and check a manifest's structure and stage layout (not the files; see :func:`verify_files`)."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataFormatError(path, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise DataFormatError(path, "manifest must be a JSON object")
    fmt = data.get("format")
    if fmt != FORMAT:
        raise DataFormatError(path, f"format is {fmt!r}; this robustbench3d reads {FORMAT!r}")
    stages = tuple(_stage(s, i, path) for i, s in enumerate(_require(data, "stages", list, path)))
    names = [s.name for s in stages]
    missing = [s for s in STAGES if s not in names]
    if missing:
        raise DataFormatError(path, f"stage {missing[0]!r} missing (a victim needs {', '.join(STAGES)})")
    if sorted(names) != sorted(STAGES):
        extra = sorted({n for n in names if n not in STAGES or names.count(n) > 1})
        raise DataFormatError(path, f"unexpected or repeated stage(s) {', '.join(map(repr, extra))}")
    manifest = Manifest(
        stages=tuple(sorted(stages, key=lambda s: STAGES.index(s.name))),
        exporter=_require(data, "exporter", dict, path), config=_require(data, "config", dict, path),
        source=_require(data, "source", dict, path), package_version=_require(data, "package_version", str, path),
        reproduce=_require(data, "reproduce", dict, path))
    check_layout(manifest, path)
    return manifest


def check_layout(manifest: Manifest, path: Path) -> None:
    """The stages fit together and fit the configuration: tensor names, point counts, input size."""
    cfg = manifest.config
    for key in ("yolo", "fpointnet", "settings"):
        _require(cfg, key, dict, path, "config")
    yolo, fpn = cfg["yolo"], cfg["fpointnet"]
    try:
        w_in, h_in = (int(v) for v in yolo["input_size"])
        n, m, classes = int(fpn["num_points"]), int(fpn["num_object_points"]), int(fpn["one_hot_dim"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(path, f"config: incomplete yolo/fpointnet configuration ({exc!r})") from None
    det = manifest.stage(DETECTOR_2D)
    _expect(det, "inputs", [(IMAGE_INPUT, (det.batch_size, 3, h_in, w_in))], path)
    if [t.name for t in det.outputs] != [head_name(i) for i in range(len(det.outputs))]:
        raise DataFormatError(path, f"stage {DETECTOR_2D!r}: outputs must be head_0, head_1, ..., got "
                                    f"{[t.name for t in det.outputs]}")
    for name in (SEGMENTATION, CENTER, BOX):
        st = manifest.stage(name)
        b = st.batch_size
        points = (b, n, 4) if name == SEGMENTATION else (b, m, 3)
        out = {SEGMENTATION: (b, n, 2), CENTER: (b, 3), BOX: (b, BOX_OUTPUTS)}[name]
        in_names, out_names = FPN_IO[name]
        _expect(st, "inputs", [(in_names[0], points), (in_names[1], (b, classes))], path)
        _expect(st, "outputs", [(out_names[0], out)], path)


def _expect(stage: StageSpec, which: str, want: list[tuple[str, tuple[int, ...]]], path: Path) -> None:
    got = [(t.name, t.shape) for t in getattr(stage, which)]
    if got != want:
        raise DataFormatError(path, f"stage {stage.name!r}: {which} {got} do not fit the configuration; "
                                    f"expected {want}")


def read_manifest(directory: str | Path) -> Manifest:
    """Read ``DIR/manifest.json``; a missing or malformed manifest raises :class:`DataFormatError` naming it."""
    path = Path(directory) / MANIFEST_FILE
    if not Path(directory).is_dir():
        raise DataFormatError(directory, "ONNX victim directory not found")
    try:
        text = read_user_text(path)
    except FileNotFoundError:
        raise DataFormatError(path, "manifest not found; an ONNX victim directory is written by "
                                    "`robustbench3d victims export-onnx`") from None
    return parse_manifest(text, path)


def verify_files(directory: str | Path, manifest: Manifest) -> None:
    """Every stage file exists and has the manifest's sha256 (else :class:`DataFormatError` naming it)."""
    for st in manifest.stages:
        path = Path(directory) / st.file
        if not path.is_file():
            raise DataFormatError(path, f"stage {st.name!r} file missing")
        got = sha256_file(path)
        if got != st.sha256:
            raise DataFormatError(path, f"sha256 {got} does not match the manifest's {st.sha256} for stage "
                                        f"{st.name!r} (file changed or corrupt; re-export it)")

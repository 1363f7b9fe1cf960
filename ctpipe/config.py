"""Strict YAML configuration: pipelines, geometries, stage parameters.

Every error names the YAML path of the bad value, the value, and what is allowed, e.g.
``pipeline.estimator.sampson_threshold: must be a number > 0 and <= 1, got -1``.

A pipeline file::

    detector: {name: sift, n_features: 4000}
    matcher: {name: brute-force, ratio: 0.8}
    estimator: {name: ransac-1pt, sampson_threshold: 8.0e-4}
    refiner: least-squares          # a bare name means the stage's default parameters
    # a stage that uses another stage names it the same way (built through the same registry):
    #   refiner: {name: projection-matching, start: {name: bundle-adjustment, loss_scale_px: 0.7}}
    pairs: {baselines: [1], loop_closure: true}   # view offsets: (i, i + k) for every k; a full
                                    # turn (known from the nominal angles) also pairs across its seam
    preprocess: {static_background: auto, detect_max_px: 1024}
                                    # static_background: detect on views less their per-pixel
                                    # median (auto: when the nominal angles span >= 180 deg); on, off
                                    # detect_max_px: a multi-scale keypoint detector (SIFT, SURF,
                                    # ORB, AKAZE, BRISK, KAZE) works on views binned to at most this
                                    # many pixels a side, keypoints in the full view's pixels
                                    # (null: the full views; the ball finder always is)
    gate: auto                      # return corrected angles only where the projections show them
                                    # better than the nominal ones (ctpipe.solve.gate); off
    # a kind left out gets DEFAULT_STAGES[kind]
    seed: 0
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml

from ctpipe._shared.checks import short_repr
from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import FIELDS as GEOMETRY_FIELDS
from ctpipe.geometry import Geometry
from ctpipe.registry import StageRegistry
from ctpipe.stages import ParamSpec, Stage, StageSpec, check_value

__all__ = ["load_yaml", "StageSpec", "PipelineConfig", "parse_pipeline", "parse_geometry", "load_geometry", "check_keys",
           "build_stage", "DEFAULT_STAGES"]

#: Stage used for a kind the pipeline file does not mention. The estimator and refiner are named
#: bare, so leaving them out and naming them bare are the same (ransac-1pt's own Sampson
#: threshold is the real-data 8e-4). The matcher adds the mutual check to brute-force's
#: defaults. The refiner is the whole-scan one: pair angles alone drift along a scan (see
#: docs/wholescan.md).
DEFAULT_STAGES = {
    "detector": {"name": "sift"},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt"},
    "refiner": {"name": "projection-matching"},
}


#: The ball-phantom pipeline (``configs/calibration-beads.yaml``, which says why each stage): what
#: ``ctpipe estimate`` runs, without a ``--pipeline``, on views that show a ball phantom
#: (:func:`ctpipe.features.ball_phantom.looks_like_ball_phantom`).
BALL_PHANTOM_PIPELINE = {
    "detector": {"name": "beads"},
    "gate": "off",
    "matcher": {"name": "all-pairs", "max_row_shift_px": 30.0},
    "estimator": {"name": "ransac-1pt", "hypotheses": "all", "scoring": "msac", "min_consensus": 0.0,
                  "one_to_one": True, "min_inliers": 3, "sampson_threshold": 1.0e-3},
    "refiner": {"name": "ball-calibration", "max_error_deg": 2.0},
    "pairs": {"baselines": [1, 2], "loop_closure": True},
    "preprocess": {"static_background": "off"},
    "seed": 0,
}


#: Nodes that aliases may add to a document beyond the ones written out. Real configurations
#: alias a few small mappings; nested aliases ("billion laughs") multiply, and a few hundred
#: bytes can stand for billions of values that a consumer (or an error message) then walks.
ALIAS_NODE_BUDGET = 100_000
#: Deepest nesting accepted; no configuration comes near it, and walking deeper recurses.
MAX_DEPTH = 100
#: Largest YAML file read (scan.yaml of 100,000 views with both angle lists is some 5 MB).
MAX_YAML_BYTES = 64 * 1024 * 1024

#: YAML 1.2 floats without a dot (``1e-3``, ``+1E5``, ``.5e3``): YAML 1.1, which PyYAML
#: follows, needs a dot in the mantissa and reads them as strings. Integers and ``1e``/``e5``
#: do not match and keep their types.
_FLOAT_EXPONENT = re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$")


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys, alias bombs and deep nesting, and reads ``1e-3``."""

    def get_single_node(self):
        node = super().get_single_node()
        if node is not None:
            _check_expansion(node)
        return node


_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_EXPONENT, list("-+0123456789."))


def _check_expansion(root: yaml.Node) -> None:
    """Refuse a node graph whose aliases expand past the budget, that refers to itself, or is too deep.

    Aliases make the composed graph a DAG sharing nodes; its expanded size is counted per
    distinct node (iteratively, so a deep document cannot exhaust the stack here).
    """
    size: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, int, bool]] = [(root, 1, False)]
    while stack:
        node, depth, children_done = stack.pop()
        key = id(node)
        if children_done:
            on_path.discard(key)
            size[key] = 1 + sum(size[id(child)] for child in _children(node))
            continue
        if key in size:
            continue
        if key in on_path:
            raise ConfigError(f"an alias refers to the node that contains it (line {node.start_mark.line + 1}); "
                              "aliases must not be recursive")
        if depth > MAX_DEPTH:
            raise ConfigError(f"nested more than {MAX_DEPTH} levels deep (line {node.start_mark.line + 1})")
        on_path.add(key)
        stack.append((node, depth, True))
        stack.extend((child, depth + 1, False) for child in _children(node))
    written = len(size)
    if size[id(root)] - written > ALIAS_NODE_BUDGET:
        raise ConfigError(f"aliases expand to {size[id(root)]:,} values from {written:,} written ones; "
                          f"at most {ALIAS_NODE_BUDGET:,} more are allowed")


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return node.value
    if isinstance(node, yaml.MappingNode):
        return [item for pair in node.value for item in pair]
    return []


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False):
    seen = set()
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *base': its keys may be overridden
            continue
        key = loader.construct_object(key_node, deep=deep)
        try:
            duplicate = key in seen
            seen.add(key)
        except TypeError:  # a list or mapping as a key: construct_mapping says so with its line
            break
        if duplicate:
            raise ConfigError(f"duplicate key {short_repr(key)} at line {key_node.start_mark.line + 1}")
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _read_text(path: Path, name: str) -> str:
    """The text of a YAML file: a regular file, a FIFO or ``/dev/fd/N`` (process substitution)."""
    if path.is_dir():
        raise ConfigError(f"{name}: is a folder; a YAML file is expected")
    try:
        with path.open("rb") as stream:
            data = stream.read(MAX_YAML_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"{name}: no such file") from None
    except OSError as exc:
        raise ConfigError(f"{name}: cannot be read ({exc.strerror or exc})") from None
    if len(data) > MAX_YAML_BYTES:
        raise ConfigError(f"{name}: larger than {MAX_YAML_BYTES // 2**20} MiB; a YAML configuration file is expected")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{name}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start}); "
                          "a YAML file must be UTF-8") from None


def load_yaml(source: str | Path, *, text: str | None = None) -> Any:
    """Parse a YAML file strictly (safe loader, no duplicate keys, YAML 1.2 floats such as ``1e-3``).

    ``source`` may be a regular file, a FIFO or ``/dev/fd/N``; with ``text``, it only names it.
    Raises :class:`ConfigError` naming the file (and the line, where there is one) for a missing
    file, a folder, text that is not UTF-8, invalid YAML, duplicate keys, aliases expanding to
    more than :data:`ALIAS_NODE_BUDGET` extra values, and nesting deeper than :data:`MAX_DEPTH`.
    """
    name = str(source)
    if text is None:
        text = _read_text(Path(source), name)
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except ConfigError as exc:
        raise ConfigError(f"{name}: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{name}: nested too deeply (at most {MAX_DEPTH} levels)") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{name}: not valid YAML{where}: {problem}") from None


def short_key(key: Any) -> str:
    """A mapping key as it goes into a YAML path: as written if a short string, else a short repr."""
    return key if isinstance(key, str) and len(key) <= 40 and key.isprintable() else short_repr(key, 40)


def check_keys(mapping: Any, path: str, *, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> Mapping:
    """Check ``mapping`` is a mapping with only ``allowed`` keys and every ``required`` one."""
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"{path}: must be a mapping with keys {', '.join(allowed)}, got {short_repr(mapping)}")
    for key in mapping:
        if key not in allowed:
            raise ConfigError(f"{path}.{short_key(key)}: unknown key; allowed: {', '.join(allowed)}")
    for key in required:
        if key not in mapping:
            raise ConfigError(f"{path}.{key}: missing; it is required")
    return mapping


def _parameter_table(cls: type[Stage]) -> dict[str, ParamSpec]:
    return {spec.name: spec for spec in cls.parameters()}


def parse_stage(value: Any, kind: str, registry: StageRegistry, path: str) -> StageSpec:
    """``value`` is a bare name or a mapping ``{name: ..., <param>: ...}``.

    A parameter that is itself a stage (``param(..., stage=kind)``) is parsed the same way, with
    its own path (``pipeline.refiner.start.loss_scale_px``), unless it is one of the words its
    annotation allows (``nominal``).
    """
    if isinstance(value, str):
        value = {"name": value}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{path}: must be a {kind} name or a mapping with 'name' and parameters, got {short_repr(value)}")
    if "name" not in value:
        raise ConfigError(f"{path}.name: missing; registered {kind}s: {', '.join(registry.names(kind))}")
    name = value["name"]
    if not isinstance(name, str):
        raise ConfigError(f"{path}.name: must be a string, got {short_repr(name)}; registered {kind}s: {', '.join(registry.names(kind))}")
    info = registry.get(kind, name, path=f"{path}.name")
    table = _parameter_table(info.cls)
    params = {}
    for key, raw in value.items():
        if key == "name":
            continue
        if key not in table:
            allowed = ", ".join(table) or "none"
            raise ConfigError(f"{path}.{short_key(key)}: unknown parameter of {kind} {name!r}; allowed: {allowed}")
        spec = table[key]
        nested = raw.to_dict() if isinstance(raw, StageSpec) else raw
        if spec.stage is not None and not spec.is_word(nested) and isinstance(nested, (str, Mapping)):
            params[key] = parse_stage(nested, spec.stage, registry, f"{path}.{key}")
        else:
            params[key] = check_value(spec, raw, f"{path}.{key}")
    return StageSpec(kind, name, params)


def build_stage(spec: StageSpec | Stage, registry: StageRegistry) -> Stage:
    """Instantiate a validated stage spec, its nested stages first, through ``registry``.

    Given a :class:`~ctpipe.stages.Stage` (one built from Python with a nested stage given by
    name), returns it with those nested specs validated and built through ``registry``.
    """
    if isinstance(spec, Stage):
        built = {}
        for param_spec in spec.parameters():
            value = getattr(spec, param_spec.name)
            if param_spec.stage is None or param_spec.is_word(value):
                continue
            if isinstance(value, StageSpec):
                value = parse_stage(value.to_dict(), param_spec.stage, registry,
                                    f"{type(spec).__name__}.{param_spec.name}")
            built[param_spec.name] = build_stage(value, registry)
        return dataclasses.replace(spec, **built) if built else spec
    params = {key: build_stage(value, registry) if isinstance(value, StageSpec) else value
              for key, value in spec.params.items()}
    return registry.get(spec.kind, spec.name).cls(**params)


@dataclass(frozen=True)
class PipelineConfig:
    """A validated pipeline description."""

    detector: StageSpec
    matcher: StageSpec
    estimator: StageSpec
    refiner: StageSpec
    baselines: tuple[int, ...] = (1,)
    seed: int | None = 0
    loop_closure: bool = True
    static_background: str = "auto"
    gate: str = "auto"
    detect_max_px: int | None = 1024
    device: str = "auto"

    def to_dict(self) -> dict:
        return {"detector": self.detector.to_dict(), "matcher": self.matcher.to_dict(),
                "estimator": self.estimator.to_dict(), "refiner": self.refiner.to_dict(),
                "pairs": {"baselines": list(self.baselines), "loop_closure": self.loop_closure},
                "preprocess": {"static_background": self.static_background, "detect_max_px": self.detect_max_px},
                "gate": self.gate, "seed": self.seed, "device": self.device}


_DEVICE = ParamSpec("device", Literal["auto", "cpu", "cuda"], "auto",
                     "where the refiner's projector and FDK run: a CUDA GPU when there is one (auto), or as named")
_PAIRS_BASELINES = ParamSpec("baselines", tuple[int, ...], (1,), "view offsets", ge=1)
_PAIRS_LOOP_CLOSURE = ParamSpec("loop_closure", bool, True, "pair the last views of a full turn with the first")
_STATIC_BACKGROUND = ParamSpec("static_background", Literal["auto", "on", "off"], "auto",
                               "subtract the per-pixel median over the views before detection")
_DETECT_MAX_PX = ParamSpec("detect_max_px", int | None, 1024,
                           "detect on views binned to at most this many pixels a side, when the detector's keypoints "
                           "hold at a working resolution (null: the full views)", ge=64, le=65536)
_SEED = ParamSpec("seed", int | None, 0, "random seed", ge=0)
_GATE = ParamSpec("gate", Literal["auto", "off"], "auto",
                  "return corrected angles only where the projections show them better than the nominal ones "
                  "(ctpipe.solve.gate); off: the refiner's angles as they are")


def _on_off(value: Any, on: str) -> Any:
    """``off`` for a YAML 1.1 boolean false (a bare ``off``), ``on`` for true; anything else as it is."""
    return value if not isinstance(value, bool) else (on if value else "off")


def parse_pipeline(mapping: Any, registry: StageRegistry, path: str = "pipeline") -> PipelineConfig:
    """Validate a pipeline mapping (see the module docstring) against ``registry``."""
    if mapping is None:
        mapping = {}
    check_keys(mapping, path, allowed=("detector", "matcher", "estimator", "refiner", "pairs", "preprocess", "gate",
                                       "seed", "device"))
    stages = {kind: parse_stage(mapping.get(kind, default), kind, registry, f"{path}.{kind}")
              for kind, default in DEFAULT_STAGES.items()}
    pairs = check_keys(mapping.get("pairs", {}), f"{path}.pairs", allowed=("baselines", "loop_closure"))
    baselines = check_value(_PAIRS_BASELINES, pairs.get("baselines", [1]), f"{path}.pairs.baselines")
    loop_closure = check_value(_PAIRS_LOOP_CLOSURE, pairs.get("loop_closure", True), f"{path}.pairs.loop_closure")
    preprocess = check_keys(mapping.get("preprocess", {}) or {}, f"{path}.preprocess",
                            allowed=("static_background", "detect_max_px"))
    # YAML 1.1 reads a bare on/off as a boolean: take it as the word the user wrote.
    static_background = check_value(_STATIC_BACKGROUND, _on_off(preprocess.get("static_background", "auto"), "on"),
                                    f"{path}.preprocess.static_background")
    detect_max_px = check_value(_DETECT_MAX_PX, preprocess.get("detect_max_px", 1024),
                                f"{path}.preprocess.detect_max_px")
    seed = check_value(_SEED, mapping.get("seed", 0), f"{path}.seed")
    gate = check_value(_GATE, _on_off(mapping.get("gate", "auto"), "auto"), f"{path}.gate")
    device = check_value(_DEVICE, mapping.get("device", "auto"), f"{path}.device")
    return PipelineConfig(**stages, baselines=tuple(sorted(set(baselines))), seed=seed, loop_closure=loop_closure,
                          static_background=static_background, gate=gate, detect_max_px=detect_max_px, device=device)


_GEOMETRY_FIELDS = {name: ParamSpec(name, annotation, None, "", **bounds)
                    for name, (annotation, bounds) in GEOMETRY_FIELDS.items()}


def parse_geometry(mapping: Any, path: str = "geometry") -> Geometry:
    """Validate a geometry mapping (keys are :class:`Geometry` fields, units in their names)."""
    optional = tuple(f.name for f in dataclasses.fields(Geometry) if f.default is not dataclasses.MISSING)
    check_keys(mapping, path, allowed=tuple(_GEOMETRY_FIELDS),
               required=tuple(k for k in _GEOMETRY_FIELDS if k not in optional))
    values = {key: check_value(_GEOMETRY_FIELDS[key], value, f"{path}.{key}") for key, value in mapping.items()}
    try:
        return Geometry(**values)
    except InputError as exc:
        raise ConfigError(str(exc).replace("geometry", path, 1)) from None


def load_geometry(source: str | Path) -> Geometry:
    """A geometry from a YAML file: the :class:`Geometry` fields, or them under one ``geometry`` key.

    The wrapped form is what ``scan.yaml`` uses; any other top-level key beside ``geometry`` is
    refused by name.
    """
    mapping = load_yaml(source)
    if isinstance(mapping, Mapping) and "geometry" in mapping:
        for key in mapping:
            if key != "geometry":
                raise ConfigError(f"{source}: {short_key(key)}: unknown top-level key; a geometry file holds "
                                  f"either the geometry fields ({', '.join(_GEOMETRY_FIELDS)}) or one 'geometry' "
                                  "mapping of them")
        mapping = mapping["geometry"]
    return parse_geometry(mapping)

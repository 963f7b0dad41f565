"""Recording metadata kept in a file a person writes (YAML or JSON): the commented template
``maglev-ros metadata init`` writes, and reading + checking such a file with the contract's own
validation (:func:`maglev_ros.contract.metadata_from_dict`, never a second validator).
"""
from __future__ import annotations

import datetime
import math
from importlib import resources
from pathlib import Path
from typing import Any

from maglev_ros.contract import Metadata, metadata_from_dict, metadata_issues
from maglev_ros.errors import UserError

__all__ = ["TEMPLATE_NAME", "template_text", "load_yaml", "json_ready", "metadata_from_file",
           "check_metadata_file"]

TEMPLATE_NAME = "metadata_template.yaml"


def template_text() -> str:
    """The commented metadata template shipped in ``maglev_ros/config``."""
    return resources.files("maglev_ros").joinpath("config", TEMPLATE_NAME).read_text(encoding="utf-8")


def _loader():
    """PyYAML's safe loader with YAML 1.2 floats: PyYAML (YAML 1.1) reads ``3.9e10`` (no dot
    before the exponent sign) as text, which people write for a Young's modulus."""
    import re

    import yaml

    class Loader(yaml.SafeLoader):
        pass

    Loader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
    Loader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
        list("-+0123456789."))
    return Loader


def load_yaml(path: str | Path, what: str = "file") -> Any:
    """A YAML (or JSON) document; one-line UserError naming the file and line on a syntax error."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read the {what} ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        return yaml.load(text, Loader=_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise UserError(f"{path}: not valid YAML{where} ({problem})") from None


def json_ready(obj: Any, source: str, path: str = "") -> Any:
    """``obj`` as plain JSON types; YAML's dates and non-string keys become one-line errors
    naming the key (the metadata travels as JSON in the bag)."""
    here = path or "(top level)"
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, str):
                raise UserError(f"{source}: metadata key {path + '.' if path else ''}{k}: "
                                f"expected a string key, got {type(k).__name__} {k!r} (quote it)")
            out[k] = json_ready(v, source, f"{path}.{k}" if path else k)
        return out
    if isinstance(obj, (list, tuple)):
        return [json_ready(v, source, f"{path}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, (datetime.date, datetime.datetime, datetime.time)):
        raise UserError(f"{source}: metadata key {here}: a YAML date/time ({obj}); "
                        "quote it to keep it as text")
    if isinstance(obj, float) and not math.isfinite(obj):
        raise UserError(f"{source}: metadata key {here}: expected a finite number, got {obj!r}")
    if obj is None or isinstance(obj, (str, int, float, bool)):
        return obj
    raise UserError(f"{source}: metadata key {here}: unsupported value {obj!r}")


def metadata_from_file(path: str | Path) -> Metadata:
    """Read and validate a metadata file (YAML or JSON) by the recording contract.

    Errors are one line: "<file>: metadata key <path>: <what was expected>"."""
    path = Path(path)
    doc = load_yaml(path, "metadata file")
    if doc is None:
        raise UserError(f"{path}: metadata file is empty (start from `maglev-ros metadata init`)")
    return metadata_from_dict(json_ready(doc, str(path)), str(path))


def check_metadata_file(path: str | Path) -> tuple[Metadata, list]:
    """The validated metadata and its soft problems (warnings, :func:`metadata_issues`)."""
    md = metadata_from_file(path)
    return md, metadata_issues(md)

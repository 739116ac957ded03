"""Settings from mappings: nested dataclasses built from a dict (e.g. a Hydra config group), checked by key."""

from __future__ import annotations

import dataclasses


def dataclass_from_dict(cls, d, path: str):
    """Build dataclass ``cls`` from mapping ``d``; nested dataclass fields take nested mappings.

    Unknown keys and values of the wrong kind raise ValueError naming the key (``path.key``); numbers are cast
    to the default's type (an integer field refuses 2.5).

    >>> from dataclasses import dataclass
    >>> @dataclass
    ... class A:
    ...     n: int = 1
    >>> dataclass_from_dict(A, {"n": 3.0}, "a")
    A(n=3)
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in dict(d).items():
        if k not in fields:
            raise ValueError(f"unknown setting {path}.{k} (known: {', '.join(fields)})")
        default = getattr(cls(), k)
        if dataclasses.is_dataclass(default):
            if not isinstance(v, dict):
                raise ValueError(f"setting {path}.{k} must be a mapping, got {v!r}")
            kwargs[k] = dataclass_from_dict(type(default), v, f"{path}.{k}")
        else:
            kwargs[k] = _checked(default, v, f"{path}.{k}")
    return cls(**kwargs)


def _checked(default, v, key: str):
    """``v`` for a field whose default is ``default``: bools stay bools, numbers become the default's type."""
    if isinstance(default, bool):
        if not isinstance(v, bool):
            raise ValueError(f"setting {key} must be true/false, got {v!r}")
    elif isinstance(default, (int, float)):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"setting {key} must be a number, got {v!r}")
        if isinstance(default, int) and not float(v).is_integer():
            raise ValueError(f"setting {key} must be an integer, got {v!r}")
        v = type(default)(v)
    elif isinstance(default, str) and not isinstance(v, str):
        raise ValueError(f"setting {key} must be a string, got {v!r}")
    return v


def preset_yaml(obj, header: str = "") -> str:
    """The YAML text of a settings dataclass instance: every key with its value and the comment of its field in
    the source (the one source of the generated presets, :mod:`runtime.presets`).

    >>> from runtime.init import InitConfig
    >>> preset_yaml(InitConfig()).splitlines()[0].split("#")[0].strip()
    'still_duration_s: 1.0'
    """
    lines = [f"# {h}".rstrip() for h in header.splitlines()]
    _emit(obj, 0, lines)
    return "\n".join(lines) + "\n"


def _emit(obj, indent: int, lines: list) -> None:
    import inspect
    import re

    comments = {}
    for cls in reversed(type(obj).__mro__):
        try:
            src = inspect.getsource(cls)
        except (OSError, TypeError):
            continue
        for m in re.finditer(r"^\s+(\w+): [^=\n]+=[^#\n]*#\s*(.+)$", src, re.M):
            comments[m.group(1)] = m.group(2).strip()
    pad = "  " * indent
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            doc = (inspect.getdoc(type(v)) or "").splitlines()
            lines.append(f"{pad}{f.name}:" + (f"  # {doc[0]}" if doc else ""))
            _emit(v, indent + 1, lines)
            continue
        text = f"{pad}{f.name}: {_yaml_value(v)}"
        c = comments.get(f.name)
        lines.append(f"{text:<46}# {c}" if c else text)


def _yaml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, float):
        r = repr(v)
        return r.replace("e", ".0e", 1) if "e" in r and "." not in r else r  # YAML 1.1 floats need the dot
    return str(v)

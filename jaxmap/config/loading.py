"""Loading configs: YAML in, frozen dataclasses out, unknown keys rejected, `--set` overrides, validation.

Every command of `jaxmap` reads one YAML file into a tree of frozen dataclasses (`jaxmap.config.schema`):
a path, or the name of a config shipped inside the package (`city` is jaxmap/configs/city.yaml).
A key the dataclass does not declare is an error that names the file, the key and the closest valid key;
`--set section.key=value` overrides any leaf; the resolved tree is written next to each run.

The loading is generic: `load_config(path, schema=MapConfig)` works for any root dataclass whose fields
are scalars, tuples of scalars or nested dataclasses.
"""
from __future__ import annotations

import dataclasses
import difflib
import os
import typing
from importlib import resources
from typing import Any, Sequence

import yaml

from jaxmap.config.rules import validate
from jaxmap.config.schema import MapConfig
from jaxmap.errors import ConfigError


def unknown_key_message(source: str, keys: Sequence[str], depth: int, here: dict[str, bool]) -> str:
    """The error for `keys[depth]`, unknown among `here` ({name: is a section} at that depth): an unknown
    section (the key goes on, or names a mapping) is matched against section names, a key against keys."""
    prefix = ".".join(keys[:depth]) + "." if depth else ""
    name, section = keys[depth], depth < len(keys) - 1
    kind = "section" if section else "key"
    pool = [n for n, is_sec in here.items() if is_sec == section] or list(here)
    close = difflib.get_close_matches(name, pool, n=1, cutoff=0.6)
    if close:
        hint = f"did you mean '{prefix}{close[0]}'?"
    else:
        hint = f"valid {kind}s here: {', '.join(prefix + n for n in pool)}"
    return f"{source}: unknown config {kind} '{prefix}{name}'; {hint}"


def _coerce(value: Any, typ: Any, where: str) -> Any:
    """Check/convert a YAML scalar to the declared field type (int->float is allowed)."""
    origin = typing.get_origin(typ)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (elem, *_rest) = typing.get_args(typ)
        return tuple(_coerce(v, elem, where) for v in value)
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0"):
            return value.lower() in ("true", "yes", "1")
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        try:
            return int(value)
        except ValueError:
            raise ConfigError(f"{where}: expected an integer, got {value!r}") from None
    if typ is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if typ is str:
        if isinstance(value, bool):  # a YAML yes / no where words are expected (`device: true`)
            return "true" if value else "false"
        if not isinstance(value, (str, int, float)):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return str(value)
    return value


def from_dict(schema: type, data: dict | None, source: str = "<config>", prefix: str = "", base: Any = None,
              check: bool = True) -> Any:
    """Build dataclass `schema` from a nested dict, rejecting unknown keys with a suggestion and (the
    root call, unless `check=False`) values that break a rule of `RULES` / `CHECKS` (see `validate`).

    Missing keys keep the defaults of `base` (an instance of `schema`; default: `schema()`), so a
    section whose default differs from its class defaults (e.g. `ImtConfig.data`) keeps them.
    """
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: section '{prefix or '<root>'}' must be a mapping, got {data!r}")
    hints = typing.get_type_hints(schema)
    fields = {f.name: f for f in dataclasses.fields(schema)}
    kwargs = {}
    for key, value in data.items():
        full = f"{prefix}{key}"
        if key not in fields:
            here = {k: dataclasses.is_dataclass(hints[k]) for k in fields}
            keys = full.split(".") + ([""] if isinstance(value, dict) else [])  # a mapping: an unknown section
            raise ConfigError(unknown_key_message(source, keys, len(keys) - 1 - isinstance(value, dict), here))
        typ = hints[key]
        if dataclasses.is_dataclass(typ):
            sub = getattr(base, key) if base is not None else _field_default(fields[key])
            kwargs[key] = from_dict(typ, value, source, prefix=f"{full}.", base=sub)
        else:
            kwargs[key] = _coerce(value, typ, f"{source}: {full}")
    cfg = dataclasses.replace(base, **kwargs) if base is not None else schema(**kwargs)
    if check and not prefix:
        validate(cfg, source)
    return cfg


def _field_default(f: dataclasses.Field) -> Any:
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None if f.default is dataclasses.MISSING else f.default


def to_dict(cfg: Any) -> dict:
    """Dataclass tree -> plain nested dict (tuples as lists), for YAML/JSON."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = to_dict(v)
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


def apply_overrides(cfg: Any, overrides: Sequence[str], source: str = "--set") -> Any:
    """Apply `section.key=value` strings (value parsed as YAML) to a dataclass tree, then `validate` it."""
    cfg, origins = _override(cfg, overrides, source)
    validate(cfg, source, origins)
    return cfg


def _override(cfg: Any, overrides: Sequence[str], source: str) -> tuple[Any, dict[str, str]]:
    """(`cfg` with the overrides applied, not yet validated; {key: the override that set it})."""
    if not overrides:
        return cfg, {}
    tree, origins = to_dict(cfg), {}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"{source} '{item}': expected section.key=value, e.g. train.iters=20")
        path, raw = item.split("=", 1)
        keys = path.strip().split(".")
        node = tree
        for depth, k in enumerate(keys):
            if not isinstance(node, dict) or k not in node:
                here = {n: isinstance(v, dict) for n, v in node.items()} if isinstance(node, dict) else {}
                raise ConfigError(unknown_key_message(f"{source} '{item}'", keys, depth, here))
            if depth == len(keys) - 1:
                if isinstance(node[k], dict):
                    raise ConfigError(f"{source} '{item}': '{path}' is a section, name one of its keys")
                node[k] = yaml.safe_load(raw)
                origins[path.strip()] = f"{source} '{item}'"
            else:
                node = node[k]
    return from_dict(type(cfg), tree, source, check=False), origins


def load_config(path: str | os.PathLike | None, overrides: Sequence[str] = (), schema: type = MapConfig) -> Any:
    """Load a YAML config into `schema`, then apply overrides. `path`: a YAML file, or the name of a
    shipped config (`city`, `room_imt`, ...: `shipped_configs()`) when no such file exists; None gives
    the defaults."""
    if path is None:
        cfg, origins = _override(schema(), overrides, "--set")
        validate(cfg, "<defaults>", origins)
        return cfg
    path = resolve_config(path)
    with open(path) as f:
        try:
            data = yaml.safe_load(f)
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {e}") from None
    cfg, origins = _override(from_dict(schema, data, source=path, check=False), overrides, "--set")
    validate(cfg, path, origins)
    return cfg


def shipped_config_dir() -> str:
    """The folder of the configs shipped inside the package (jaxmap/configs, package data; the repository's
    configs/ links to it)."""
    return os.fspath(resources.files("jaxmap").joinpath("configs"))


def shipped_configs() -> list[str]:
    """The names of the shipped configs (`city`, `room_imt`, ...), sorted: what `load_config` and every
    command accept in place of a path."""
    return sorted(n[:-5] for n in os.listdir(shipped_config_dir()) if n.endswith(".yaml"))


def resolve_config(given: str | os.PathLike) -> str:
    """The YAML file a config argument names: an existing file as given (a path wins over a name), else
    the shipped config of that name (`city` or `city.yaml`). Neither: a ConfigError naming what was
    given and the shipped names."""
    given = os.fspath(given)
    if os.path.isfile(given):
        return given
    name, names = given[:-5] if given.endswith(".yaml") else given, shipped_configs()
    if name and os.sep not in name and name in names:
        return os.path.join(shipped_config_dir(), f"{name}.yaml")
    close = difflib.get_close_matches(os.path.basename(name), names, n=1, cutoff=0.6)
    hint = f"did you mean '{close[0]}'? " if close else ""
    raise ConfigError(f"config not found: {given} is neither a file nor a shipped config; {hint}give a YAML path "
                      f"or one of: {', '.join(names)} (`jaxmap configs` lists them)")


def shipped_config_path(name: str) -> str | None:
    """The file of the shipped config `name` (`city.yaml` or `city`), or None when there is none."""
    name = name[:-5] if name.endswith(".yaml") else name
    return os.path.join(shipped_config_dir(), f"{name}.yaml") if name in shipped_configs() else None


def config_from_args(args, schema: type = MapConfig) -> Any:
    """The config of a mapping command: `args.config` with `--set` overrides, then `--data` and `--out`
    (which override data.path and output)."""
    overrides = list(args.overrides)
    if getattr(args, "data", None):
        overrides.append(f"data.path={args.data}")
    if getattr(args, "out", None):
        overrides.append(f"output={args.out}")
    return load_config(args.config, overrides, schema=schema)


def save_config(cfg: Any, path: str | os.PathLike) -> None:
    """Write the resolved config as YAML (what the run actually used)."""
    with open(path, "w") as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)

"""One way to check a config: typed dataclasses with rules on their fields.

Every entry point's config (``conf/label.yaml``, ``eval.yaml``, ``train.yaml``, ``export.yaml``) extends a
structured config, a dataclass registered in Hydra's ConfigStore (:func:`store`), and so does every teacher block.
Two things are checked, both from those dataclasses:

* the type of each value and the set of keys: by OmegaConf while Hydra composes the config (``limit=abc``,
  ``trainer.max_stepz=3``), before any work; :func:`type_error_line` turns its error into the one line users see;
* what a type cannot say (an integer >= 1, one of a few words): each field's :func:`setting` carries a ``rule``
  (a key of :data:`RULES`) or ``choices``; :func:`check_config` checks every field of a composed config against
  them (:class:`OptionError`, one line naming the option), and the teacher's dataclasses check the same rules on
  construction (:func:`broken_rule`).

What neither can say (a path that must exist, a value that depends on another) stays with the code that uses it.
:func:`signature_schema` writes the dataclass of a callable's keyword arguments (Lightning's ``Trainer``), so its
options are typed and a misspelt one is refused like ours.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect
import math
import operator
import types
import typing
from dataclasses import field

from icpflow.core.stops import raise_stop_behind

#: what each ``rule`` of :func:`setting` accepts, as the error message says it
RULES = {
    "positive": "a number > 0",
    "non_negative": "a number >= 0",
    "fraction": "a number in [0, 1]",
    "number": "a number",
    "count": "an integer >= 1",
    "count_or_zero": "an integer >= 0",
    "odd_count": "an odd integer >= 1",
    "count_or_none": "None or an integer >= 1",
    "integer": "an integer",
    "flag": "true or false",
    "pixel_size": "[width,height] in pixels",
}


class OptionError(ValueError):
    """An option's value cannot be used (wrong type, breaks its rule, unknown). One line naming the option."""


def accepts(rule: str, value) -> bool:
    """Whether ``value`` obeys ``rule`` (a key of :data:`RULES`)."""
    is_int = isinstance(value, int) and not isinstance(value, bool)
    is_number = (is_int or isinstance(value, float)) and not math.isnan(value)
    if rule == "pixel_size":
        return (
            isinstance(value, (list, tuple))
            and len(value) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
        )
    return {
        "positive": lambda: is_number and value > 0,
        "non_negative": lambda: is_number and value >= 0,
        "fraction": lambda: is_number and 0 <= value <= 1,
        "number": lambda: is_number,
        "count": lambda: is_int and value >= 1,
        "count_or_zero": lambda: is_int and value >= 0,
        "odd_count": lambda: is_int and value >= 1 and value % 2 == 1,
        "count_or_none": lambda: value is None or (is_int and value >= 1),
        "integer": lambda: is_int,
        "flag": lambda: isinstance(value, bool),
    }[rule]()


def setting(default, rule: str | None = None, *, choices: tuple | None = None, old: str | None = None):
    """A config field: its ``default``, the ``rule`` its value obeys (a key of :data:`RULES`) or its allowed
    ``choices``, and its ``old`` flat name (the teacher's, before the per-step blocks) when it had another one. A
    mutable default (a list) is copied for each instance."""
    if rule is not None and rule not in RULES:
        raise ValueError(f"setting: unknown rule {rule!r}")
    metadata = {"rule": rule, "choices": choices, "old": old}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def _shown(value) -> str:
    return "null" if value is None else str(value)


def broken_rule(f: dataclasses.Field, value) -> str | None:
    """What is wrong with ``value`` for field ``f`` (``must be ..., got ...``), or None when it obeys the field's
    rule or choices (a field without either accepts anything)."""
    choices, rule = f.metadata.get("choices"), f.metadata.get("rule")
    if choices is not None and value not in choices:
        return f"must be one of {', '.join(map(_shown, choices))}, got {value!r}"
    if rule is not None and not accepts(rule, value):
        return f"must be {RULES[rule]}, got {value!r}"
    return None


class Checked:
    """A settings dataclass's base: ``__post_init__`` checks every field against its ``setting`` rule or choices
    (ValueError, one line naming the class and the field)."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            problem = broken_rule(f, getattr(self, f.name))
            if problem:
                raise ValueError(f"{type(self).__name__}: {f.name} {problem}")


def _allows_none(hint) -> bool:
    return hint is typing.Any or type(None) in typing.get_args(hint)


def check_config(cfg, prefix: str = "") -> None:
    """Check every field of the composed config ``cfg`` (and of its typed sub-blocks) that has a rule or choices,
    and refuse keys its dataclass does not have (``+limt=3``): :class:`OptionError`, e.g. ``workers must be an
    integer >= 1, got 0``. None passes where the field's type allows it (null: the default's meaning). Paths given
    as ``~/...`` are expanded first (:func:`expand_home`)."""
    from omegaconf import DictConfig, OmegaConf

    if not prefix:
        expand_home(cfg)
    for key in cfg:  # the blocks first: a value that others interpolate (dataset.eval_crop) is named where it is set
        if OmegaConf.is_missing(cfg, key):
            continue
        child = cfg._get_node(key)
        if isinstance(child, DictConfig) and not child._is_none() and not child._is_interpolation():
            check_config(child, f"{prefix}{key}.")
    kind = OmegaConf.get_type(cfg)
    if not dataclasses.is_dataclass(kind):
        if "_target_" in cfg:
            check_target_arguments(cfg, prefix)
        return
    known = {f.name: f for f in dataclasses.fields(kind)}
    hints = typing.get_type_hints(kind)
    for key in cfg:
        if key not in known:
            raise OptionError(unknown_words(key, known, prefix))
        f = known[key]
        if f.metadata.get("rule") is None and f.metadata.get("choices") is None:
            continue
        value = cfg[key]
        value = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
        if value is None and _allows_none(hints[key]):
            continue
        problem = broken_rule(f, value)
        if problem:
            raise OptionError(f"{prefix}{key} {problem}")


#: Hydra's own keys of a ``_target_`` node
HYDRA_KEYS = ("_target_", "_partial_", "_convert_", "_recursive_", "_args_")
#: the kinds of value an argument takes, and how to say them: (types of the default or annotation, accepted, words)
_KINDS = (
    ((bool,), (bool,), "true or false"),
    ((int, float), (int, float), "a number"),
    ((str,), (str,), "a text"),
    ((list, tuple), (), "a list, e.g. [a,b]"),
)


def _argument_kind(parameter, hint):
    """(accepted types (empty: a list), words, None allowed) of an argument, from its annotation (every member of a
    union) or else its default; None where neither says (an object, ``Any``)."""
    members = typing.get_args(hint) if _is_union(hint) else (typing.get_origin(hint) or hint,)
    if hint is None or hint is typing.Any:
        default = parameter.default
        members = () if default is inspect.Parameter.empty or default is None else (type(default),)
    found = [
        entry
        for entry in _KINDS
        if any(isinstance(m, type) and issubclass(m, entry[0]) for m in members if m is not type(None))
    ]
    if not found:
        return None  # nothing a config value can be checked against (an object): leave the value to the target
    accepted = tuple(t for entry in found for t in entry[1])
    lists = any(not entry[1] for entry in found)
    return accepted, lists, " or ".join(entry[2] for entry in found), type(None) in members


def check_target_arguments(node, prefix: str) -> None:
    """The arguments of a ``_target_`` node (``model``, ``optim``, ``scheduler``, ...) against its target's
    signature, before it is built: a name it does not take (``+model.correlation_levls=[1]``) is refused with the
    nearest it does take; a value of another kind than the argument's annotation (or default) asks for (a number
    for a list, text for a number) names the argument. :class:`OptionError`, one line; a target that cannot be
    imported is left to Hydra."""
    from hydra.utils import get_object
    from omegaconf import DictConfig, ListConfig, OmegaConf

    try:
        target = get_object(str(node["_target_"]))
        parameters = inspect.signature(target).parameters
        hints = typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
    except Exception as error:  # noqa: BLE001 - an unknown target is Hydra's error to report, with its own words
        raise_stop_behind(error)
        return
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return
    taken = [name for name in parameters if name not in ("self", "params")]
    for key in node:
        if key in HYDRA_KEYS:
            continue
        if key not in parameters:
            raise OptionError(f"{unknown_words(key, taken, prefix)} of {node['_target_']}")
        kind = _argument_kind(parameters[key], hints.get(key))
        if kind is None or OmegaConf.is_missing(node, key) or node._get_node(key)._is_interpolation():
            continue
        accepted, lists, words, optional = kind
        value = node[key]
        if (value is None and (optional or parameters[key].default is None)) or isinstance(value, DictConfig):
            continue  # a block builds an object of its own (a nested _target_)
        ok = (lists and isinstance(value, ListConfig)) or isinstance(value, accepted)
        if isinstance(value, bool) and bool not in accepted:
            ok = False
        if not ok:
            raise OptionError(f"{prefix}{key}={value}: expected {words}, got {value!r}")


def unknown_words(key: str, known, prefix: str) -> str:
    """``<prefix><key> is not an option (did you mean <prefix>X?)`` for a ``key`` not among ``known`` names."""
    close = difflib.get_close_matches(key, list(known), n=1)
    return f"{prefix}{key} is not an option" + (f" (did you mean {prefix}{close[0]}?)" if close else "")


# ---------------------------------------------------------------------------------------------------- types

_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a text"}


def type_words(hint) -> str:
    """What a value of type ``hint`` is, in words (``an integer``, ``a number``, ``a list, e.g. [a,b]``)."""
    members = [m for m in typing.get_args(hint) if m is not type(None)] if _is_union(hint) else [hint]
    if set(members) == {int, float}:
        return "a number"
    words = []
    for member in members:
        origin = typing.get_origin(member) or member
        if origin in (list, tuple):
            words.append("a list, e.g. [a,b]")
        elif origin is dict or dataclasses.is_dataclass(origin):
            words.append("a block of settings")
        else:
            words.append(_WORDS.get(origin, getattr(origin, "__name__", str(origin))))
    return " or ".join(dict.fromkeys(words))


def _is_union(hint) -> bool:
    return typing.get_origin(hint) in (typing.Union, types.UnionType)


def type_error_line(error) -> str | None:
    """The line for OmegaConf's error about an override (Hydra's ``Error merging override K=V`` /
    ``Could not override 'K'`` with the OmegaConf error as its cause), or None when it is about something else:
    ``K=V: expected <words>, got 'V' (the default is D)``, ``K=V: K is a block of settings, give one of its fields``,
    ``K=V: <parent> has no option <name> (did you mean ...?)``."""
    from omegaconf import OmegaConf
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, ValidationError

    cause = error.__cause__
    override = _override_of(str(error))
    kind = getattr(cause, "object_type", None)
    full_key, key = getattr(cause, "full_key", None), getattr(cause, "key", None)
    if override is None or full_key is None:
        return None
    if not dataclasses.is_dataclass(kind):  # a plain block (a _target_ node: model, optim, ...): its own keys
        parent = getattr(cause, "parent_node", None)
        if isinstance(cause, (ConfigAttributeError, ConfigKeyError)) and parent is not None:
            prefix = full_key[: -len(str(key))] if str(full_key).endswith(str(key)) else ""
            known = [name for name in parent.keys() if name not in HYDRA_KEYS]
            return f"{override}: {unknown_words(str(key), known, prefix)}"
        return None
    given = override.split("=", 1)[1] if "=" in override else ""
    if isinstance(cause, (ConfigAttributeError, ConfigKeyError)):
        prefix = full_key[: -len(str(key))] if str(full_key).endswith(str(key)) else ""
        known = [f.name for f in dataclasses.fields(kind)]
        return f"{override}: {unknown_words(str(key), known, prefix)}"
    if not isinstance(cause, ValidationError):
        return None
    hint = typing.get_type_hints(kind).get(str(key))
    if hint is None:
        return None
    if dataclasses.is_dataclass(hint) or "is not a subclass" in str(cause):
        return f"{override}: {full_key} is a block of settings, give one of its fields ({full_key}.<field>=...)"
    root = cause.parent_node._get_root() if cause.parent_node is not None else None
    default = OmegaConf.select(root, full_key, default=None, throw_on_missing=False) if root is not None else None
    default = OmegaConf.to_container(default) if OmegaConf.is_config(default) else default
    hint_text = f" (the default is {default})" if default is not None else ""
    return f"{override}: expected {type_words(hint)}, got {given!r}{hint_text}"


def _override_of(message: str) -> str | None:
    """``K=V`` of Hydra's ``Error merging override K=V`` / the key of ``Could not override 'K'. ... use +K=V``."""
    first = message.strip().splitlines()[0] if message.strip() else ""
    if first.startswith("Error merging override "):
        return first[len("Error merging override ") :].strip()
    if first.startswith("Could not override "):
        for line in message.splitlines():
            if "use +" in line:
                return line.split("use +", 1)[1].strip()
    return None


# ---------------------------------------------------------------------------------------------------- schemas


def _omegaconf_type(hint):
    """The closest type OmegaConf can check for a signature's annotation: a primitive, an Optional or a union of
    primitives (Literal values by their types); Any for the rest (a list, an object)."""
    primitives = (int, float, bool, str)
    if hint in primitives:
        return hint
    members = typing.get_args(hint) if _is_union(hint) else (hint,)
    optional = type(None) in members
    kinds: list[type] = []
    for member in members:
        if member is type(None):
            continue
        if typing.get_origin(member) is typing.Literal:
            kinds += [type(value) for value in typing.get_args(member)]
        elif member in primitives:
            kinds.append(member)
        else:
            return typing.Any
    kinds = list(dict.fromkeys(kinds))
    if not kinds:
        return typing.Any
    union = functools.reduce(operator.or_, kinds)
    return union | None if optional else union


def signature_schema(target, name: str, exclude: tuple[str, ...] = ()) -> type:
    """A dataclass of ``target``'s keyword arguments (``target`` a class or function): each typed as OmegaConf can
    check it, defaulting to the signature's default; ``exclude``: arguments the code passes itself. A config node of
    this type holds every argument, so it can be passed as ``target(**node)``."""
    entries = []
    parameters = inspect.signature(target).parameters
    hints = typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
    for parameter in parameters.values():
        if parameter.name in ("self", *exclude) or parameter.kind in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD):
            continue
        if parameter.default is inspect.Parameter.empty:
            raise ValueError(f"signature_schema: {target.__name__}'s {parameter.name} has no default")
        entries.append((parameter.name, _omegaconf_type(hints.get(parameter.name, typing.Any)), parameter.default))
    return dataclasses.make_dataclass(name, entries)


def store(name: str, node, group: str | None = None) -> None:
    """Register the dataclass ``node`` in Hydra's ConfigStore as ``name`` (in ``group``), for a config's defaults
    list to extend, and the resolvers of the folders Hydra makes before any code of ours runs: ``home``
    (``${home:${out_dir}}``: ``~`` expanded) and ``run_folder`` (:func:`run_folder`). Idempotent."""
    import os

    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    ConfigStore.instance().store(name=name, node=node, group=group)
    if not OmegaConf.has_resolver("home"):
        OmegaConf.register_new_resolver("home", lambda path: os.path.expanduser(str(path)))
    if not OmegaConf.has_resolver("run_folder"):
        OmegaConf.register_new_resolver("run_folder", run_folder)


def run_folder(default: str, out_dir=None) -> str:
    """Hydra's folder for a launch's config and log (``conf/hydra/default.yaml``): ``default`` (relative to the
    working directory) where that directory is writable, else ``<out_dir>/.hydra``: a run started from a read-only
    folder (an installed checkout, a shared drive) writes only where its results go."""
    import os

    if os.access(".", os.W_OK) or not out_dir:
        return str(default)
    return os.path.join(os.path.expanduser(str(out_dir)), ".hydra")


def expand_home(cfg) -> None:
    """Every text option of ``cfg`` (not an interpolation) that starts with ``~``, expanded to the home folder in
    place: quoted (``out_dir='~/x'``) no shell expands it, and it became a literal ``./~/x`` folder."""
    import os

    from omegaconf import DictConfig, ListConfig

    for key in list(cfg.keys()) if isinstance(cfg, DictConfig) else range(len(cfg)):
        node = cfg._get_node(key)
        if node is None or node._is_interpolation() or node._is_missing():
            continue
        value = node._value()
        if isinstance(node, (DictConfig, ListConfig)):
            expand_home(node)
        elif isinstance(value, str) and value.startswith("~"):
            cfg[key] = os.path.expanduser(value)

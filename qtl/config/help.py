"""``qtl-train --help`` and the configuration reference page, rendered from the schema and the installed configs.

Both walk the same dataclasses (:mod:`qtl.config.schema`, :mod:`qtl.config.groups`) for every key's default and
description, and the config tree (``qtl.configs``) for each group's options and their one-line summaries.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import re
import typing
from collections.abc import Iterator

from omegaconf import DictConfig, OmegaConf

from qtl.config.groups import GROUP_SCHEMAS
from qtl.config.schema import TrainConfig

HELP_WIDTH = 44  # column of the descriptions in --help


def _dataclass_of(hint: object) -> type | None:
    """The dataclass a field's type names, ``Optional[...]`` unwrapped; None for a leaf."""
    for candidate in (hint, *typing.get_args(hint)):
        if isinstance(candidate, type) and dataclasses.is_dataclass(candidate):
            return candidate
    return None


def _keys(schema: type, prefix: str = "") -> Iterator[tuple[str, str, str]]:
    """(dotted key, default, description) of every leaf of ``schema``, nested dataclasses expanded."""
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        if f.name.startswith("_") or (not prefix and f.name in GROUP_SCHEMAS):
            continue  # `_target_` and friends; the groups are listed per option
        key = f"{prefix}{f.name}"
        nested = _dataclass_of(hints[f.name])
        if nested is not None and typing.get_origin(hints[f.name]) is list:  # a list of entries: key[i].field
            yield key, "[]", f.metadata.get("help", "")
            yield from _keys(nested, f"{key}[i].")
            continue
        if nested is not None:
            yield from _keys(nested, f"{key}.")
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        shown = OmegaConf.to_yaml({"v": default}).strip().removeprefix("v:").strip()
        yield key, shown, f.metadata.get("help", "")


def _entry(key: str, default: str, text: str, indent: str) -> str:
    """One aligned line of the key list (two when the key is long)."""
    head = f"{indent}{key} [{default}]"
    return f"{head:<{HELP_WIDTH}} {text}" if len(head) < HELP_WIDTH else f"{head}\n{'':<{HELP_WIDTH}} {text}"


def help_text() -> str:
    """The key list of ``qtl-train --help``: every key with its default and description, then each group's options."""
    lines = ["== Keys (key=value; defaults in brackets) =="]
    lines += [_entry(key, default, text, "  ") for key, default, text in _keys(TrainConfig)]
    for group, options in GROUP_SCHEMAS.items():
        lines += ["", f"== {group}=<option> =="]
        for option, schema in options.items():
            lines.append(f"  {group}={option}: {_summary(schema)}")
            lines += [_entry(key, default, text, "    ") for key, default, text in _keys(schema, f"{group}.")]
    return "\n".join(lines)


def _summary(schema: type) -> str:
    """A group option's one-line description: its schema's docstring."""
    return (schema.__doc__ or "").strip()


# -- the installed config groups ---------------------------------------------------------------------------

CONFIG_PACKAGE = "qtl.configs"
SCHEMA_SUFFIX = "_schema"  # ConfigStore entries that type an option: no choice of their own
_PACKAGE_LINE = re.compile(r"#\s*@package\b")
# The end of a YAML comment's first sentence: a full stop before a capital or the end, not "Eq." or "Fig.".
_SENTENCE_END = re.compile(r"(?<!\bEq)(?<!\bFig)(?<!\bTab)\.(?=\s+[A-Z]|\s*$)")
SUMMARY_LENGTH = 160  # a longer first sentence is cut at its first clause


def _first_clause(sentence: str) -> str:
    """``sentence`` up to its first ``:`` or ``;`` outside parentheses and brackets, as a sentence."""
    depth = 0
    for i, char in enumerate(sentence):
        depth += (char in "([") - (char in ")]")
        if depth == 0 and char in ":;" and sentence[i + 1 : i + 2] == " ":
            return sentence[:i] + "."
    return sentence


def _comment_summary(text: str) -> str:
    """The first sentence of a YAML file's leading comment (``# @package`` lines skipped); empty without one.

    A sentence longer than :data:`SUMMARY_LENGTH` is cut at its first clause.
    """
    parts: list[str] = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        if not _PACKAGE_LINE.match(line):
            parts.append(line.lstrip("#").strip())
    comment = " ".join(part for part in parts if part)
    end = _SENTENCE_END.search(comment)
    sentence = comment if end is None else comment[: end.end()]
    return _first_clause(sentence) if len(sentence) > SUMMARY_LENGTH else sentence


def config_groups() -> dict[str, list[tuple[str, str]]]:
    """Each group of the installed config tree with its options and their one-line descriptions, by name.

    The options are the group's YAML files (``qtl.configs/<group>/<option>.yaml``), each described by the first
    sentence of its leading comment; the ``<option>_schema`` entries that type them in the ConfigStore are not
    choices. Hydra's own groups (``hydra/...``) are left out, as Hydra's ``--help`` leaves them out.
    """
    groups: dict[str, list[tuple[str, str]]] = {}
    for folder in sorted(importlib.resources.files(CONFIG_PACKAGE).iterdir(), key=lambda entry: entry.name):
        if not folder.is_dir() or folder.name == "hydra":
            continue
        options = [
            (file.name.removesuffix(".yaml"), _comment_summary(file.read_text(encoding="utf-8")))
            for file in sorted(folder.iterdir(), key=lambda entry: entry.name)
            if file.name.endswith(".yaml") and not file.name.removesuffix(".yaml").endswith(SCHEMA_SUFFIX)
        ]
        if options:
            groups[folder.name] = options
    return groups


def default_options() -> dict[str, str | None]:
    """The option ``train.yaml`` chooses for each group (None: no option unless one is given)."""
    train = OmegaConf.load(importlib.resources.files(CONFIG_PACKAGE).joinpath("train.yaml").open(encoding="utf-8"))
    chosen: dict[str, str | None] = {}
    for entry in train.defaults:
        if isinstance(entry, DictConfig):
            for group, option in entry.items():
                if "/" not in str(group) and not str(group).startswith("override"):
                    chosen[str(group)] = option
    return chosen


def groups_text() -> str:
    """The group list of ``qtl-train --help``: ``group: option, option, ...`` per installed group."""
    return "\n".join(f"{group}: {', '.join(name for name, _ in options)}" for group, options in config_groups().items())


# -- the configuration reference (docs/guide/configuration.md) ------------------------------------------------

REFERENCE_PAGE = "docs/guide/configuration.md"
REFERENCE_COMMAND = f"python -m qtl.config --markdown > {REFERENCE_PAGE}"
REFERENCE_INTRO = """\
# Configuration reference

Every key `qtl-train` reads, with its default and its meaning: the list `qtl-train --help` prints, from the same
schema (the dataclasses of `qtl/config/schema.py` and `qtl/config/groups.py`). Choose a group's option with
`group=option` and set a key with `key=value`, e.g. `qtl-train task=mountaincar task.env.power=0.5 optimizer=adam
optimizer.lr=0.005`; a key the schema does not know, or a value of the wrong type, fails before any work. `???`
marks a key without a default (the task file or the option sets it), `${key}` a default read from another key,
`null` an unset optional value.
"""


def _cell(text: str) -> str:
    """``text`` safe in a Markdown table cell: pipes escaped, no emphasis or HTML read into it."""
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("*", "\\*").replace("<", "&lt;")


def _code(text: str) -> str:
    """``text`` as an inline code span (a pipe inside one does not split a table cell; a backtick lengthens it)."""
    fence = "``" if "`" in text else "`"
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def _key_table(rows: list[tuple[str, str, str]]) -> list[str]:
    """The ``key | default | meaning`` table of ``rows`` (dotted key, default, description)."""
    lines = ["| key | default | meaning |", "| --- | --- | --- |"]
    lines += [f"| {_code(key)} | {_code(default)} | {_cell(text)} |" for key, default, text in rows]
    return lines


def _option_table(group: str, options: list[tuple[str, str]], default: str | None) -> list[str]:
    """The ``option | description`` table of a group, its default option marked."""
    lines = ["| option | description |", "| --- | --- |"]
    for name, text in options:
        mark = " (default)" if name == default else ""
        lines.append(f"| {_code(f'{group}={name}')}{mark} | {_cell(text)} |")
    return lines


def _heading_text(text: str) -> str:
    """A field's description as a sentence under its section's heading."""
    text = _cell(text)
    return f"{text[:1].upper()}{text[1:]}."


def reference_markdown() -> str:
    """The configuration reference page: the keys of ``--help`` (the same walk, the same text), a section per group.

    Top-level keys first, then a section per node of :class:`TrainConfig` in its order (``task``, the groups with a
    table per option, ``transfer``, ``sweep``, ``kernels``), then the preset groups (``approach``, ...).
    """
    keys = list(_keys(TrainConfig))
    groups = config_groups()
    defaults = default_options()
    hints = typing.get_type_hints(TrainConfig)
    lines = [f"<!-- Generated by `{REFERENCE_COMMAND}` from qtl/config/: edit there, not here. -->", "",
             REFERENCE_INTRO, "## Config groups", "", "| group | options | default |", "| --- | --- | --- |"]
    for group, options in groups.items():
        chosen = defaults.get(group)
        names = ", ".join(_code(name) for name, _ in options)
        lines.append(f"| {_code(group)} | {names} | {_code('null' if chosen is None else chosen)} |")
    lines += ["", "## Top-level keys", "", *_key_table([row for row in keys if "." not in row[0]])]
    nodes = [f for f in dataclasses.fields(TrainConfig)
             if f.name in GROUP_SCHEMAS or f.name in groups or _dataclass_of(hints[f.name]) is not None]
    for node in nodes:
        lines += ["", f"## {node.name}", "", _heading_text(node.metadata.get("help", ""))]
        if node.name not in GROUP_SCHEMAS:
            if node.name in groups:
                lines += ["", *_option_table(node.name, groups[node.name], defaults.get(node.name))]
            lines += ["", *_key_table([row for row in keys if row[0].startswith(f"{node.name}.")])]
            continue
        if defaults.get(node.name) is not None:
            lines[-1] += f" Default: `{node.name}={defaults[node.name]}`."
        for option, schema in GROUP_SCHEMAS[node.name].items():
            rows = list(_keys(schema, f"{node.name}."))
            lines += ["", f"### {node.name}={option}", "", _cell(_summary(schema)), ""]
            lines += _key_table(rows) if rows else ["No keys of its own."]
    presets = [group for group in groups if group not in {node.name for node in nodes}]
    if presets:
        lines += ["", "## Presets", "", "Groups whose options set keys of several nodes at once "
                  "(`# @package _global_`), applied over `train.yaml`."]
        for group in presets:
            lines += ["", f"### {group}", "", *_option_table(group, groups[group], defaults.get(group))]
    return "\n".join(lines) + "\n"



HELP_TEMPLATE = """\
qtl-train: learn a task with PILCO, from scratch or with qualitative transfer from a source run.

  qtl-train [group=option ...] [key=value ...]      e.g. qtl-train task=mountaincar task.env.power=0.5 seed=3
  qtl-train resume=<run dir> [episodes=N]           continue an interrupted run
  qtl-train --cfg job [overrides]                   print the composed config

== Config groups (group=option) ==
{groups}

{keys}

Bad input fails before any work with one line saying what to fix (HYDRA_FULL_ERROR=1: the traceback).
Hydra's own flags: --hydra-help
"""

"""The configuration reference page (docs/guide/configuration.md) is generated from the schema, and up to date."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from qtl.config import (
    GROUP_SCHEMAS,
    REFERENCE_COMMAND,
    REFERENCE_PAGE,
    TrainConfig,
    config_groups,
    default_options,
    groups_text,
    help_text,
    reference_markdown,
)
from qtl.config.help import _keys

ROOT = Path(__file__).resolve().parents[1]


def every_key() -> list[tuple[str, str, str]]:
    """Every (key, default, description) of the schema: the top level's, then each group option's."""
    rows = list(_keys(TrainConfig))
    for group, options in GROUP_SCHEMAS.items():
        for schema in options.values():
            rows += _keys(schema, f"{group}.")
    return rows


def test_the_committed_page_is_the_generated_one():
    page = ROOT / REFERENCE_PAGE
    assert page.read_text(encoding="utf-8") == reference_markdown(), (
        f"{REFERENCE_PAGE} is stale: regenerate it with `{REFERENCE_COMMAND}`"
    )


def test_the_page_says_how_it_is_generated():
    first = reference_markdown().splitlines()[0]
    assert first.startswith("<!--") and REFERENCE_COMMAND in first


def test_every_schema_key_is_in_the_help_and_on_the_page():
    help_, page = help_text(), reference_markdown()
    for key, default, _ in every_key():
        assert f"{key} [{default}]" in help_, key
        assert f"| `{key}` | `{default}` |" in page, key


def test_every_option_is_on_the_page_and_no_schema_is_a_choice():
    page, listed = reference_markdown(), groups_text()
    groups = config_groups()
    assert set(GROUP_SCHEMAS) <= set(groups)
    for group, schemas in GROUP_SCHEMAS.items():
        assert [name for name, _ in groups[group]] == sorted(schemas), group
        for option in schemas:
            assert f"### {group}={option}" in page
    assert "_schema" not in listed and "_schema" not in page
    for group, options in groups.items():
        assert f"{group}: {', '.join(name for name, _ in options)}" in listed
        for name, summary in options:
            assert summary, f"configs/{group}/{name}.yaml has no leading comment to describe it"


def test_the_defaults_are_train_yaml_s():
    chosen = default_options()
    assert chosen["task"] == "cartpole" and chosen["propagation"] == "moment_matching" and chosen["rule"] == "none"
    assert chosen["approach"] is None


@pytest.mark.parametrize("argv", [["--markdown"], []])
def test_the_module_prints_the_page_or_the_key_list(argv):
    done = subprocess.run([sys.executable, "-m", "qtl.config", *argv], cwd=ROOT, capture_output=True, timeout=120)
    assert done.returncode == 0, done.stderr.decode()
    expected = reference_markdown() if argv else help_text() + "\n"
    assert done.stdout.decode("utf-8") == expected

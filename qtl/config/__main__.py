"""``python -m qtl.config --markdown``: print the configuration reference page (else the ``--help`` key list)."""

from __future__ import annotations

import sys

from qtl.config.help import REFERENCE_COMMAND, help_text, reference_markdown


def main(argv: list[str] | None = None) -> None:
    """``python -m qtl.config --markdown``: print the configuration reference page (else the ``--help`` key list)."""
    args = sys.argv[1:] if argv is None else argv
    if args not in ([], ["--markdown"]):
        raise SystemExit(f"usage: {REFERENCE_COMMAND}")
    sys.stdout.reconfigure(encoding="utf-8")  # type: ignore[union-attr]
    sys.stdout.write(reference_markdown() if args else help_text() + "\n")


if __name__ == "__main__":
    main()

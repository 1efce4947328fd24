"""One truth about which model runs: every page and docstring names the code's default.

The default is read from `taptr.weights.registry` (`DEFAULT_MODEL`, and `FALLBACK_MODEL` when it
cannot be had), so the test follows the code. A claim is checked where text says which model is the
default: a name followed by "(default)", a name right before "default model", the first model that a
clause starting with "default" names, and the comment on a ``from_pretrained()`` line that names no
model. Model names are those of published and bundled weights (`taptr.weights.registry.WEIGHTS`,
`taptr.weights.registry.BUNDLED`), so a new name in a table is covered without changing this file;
preset names ("small", "tiny") are ordinary words too often to be read as claims.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from taptr.weights.registry import BUNDLED, DEFAULT_MODEL, FALLBACK_MODEL, MANUAL, WEIGHTS

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted(
    [
        REPO / "README.md",
        *(REPO / "docs").glob("*.md"),
        *(REPO / "examples").glob("*"),
        *(REPO / "src" / "taptr").rglob("*.py"),
    ]
)
STATING_PAGES = [
    "README.md",
    "docs/GETTING_STARTED.md",
    "docs/FAQ.md",
    "docs/CLI.md",
    "docs/API.md",
    "examples/README.md",
]
"""Pages a new user reads for which model runs: each states the default, with its licence."""

# phrases that name a model without its name; the bundled model is the fallback
PHRASES = {
    r"\bbundled\b": FALLBACK_MODEL,
    r"\bpaper's\s+(?:released\s+)?(?:TAPTRv2\s+)?weights": "",
}
NAMES = sorted([*WEIGHTS, *MANUAL, *BUNDLED], key=len, reverse=True)
MENTION = re.compile(
    "|".join([*(rf"(?<![\w-]){re.escape(name)}(?![\w-])" for name in NAMES), *PHRASES])
)
CLAUSE_END = re.compile(r"[.;]\s|\n\s*\n|[|)]")
NEAR = 60
"""How close after "default:" a model must be named to be what the clause calls the default."""


def _named(mention: str) -> str:
    """The model a mention stands for (the paper's weights: the default)."""
    for phrase, name in PHRASES.items():
        if re.fullmatch(phrase, mention):
            return name or DEFAULT_MODEL
    return mention


def _first_model(text: str) -> str | None:
    found = MENTION.search(text)
    return _named(found.group(0)) if found else None


def _clause(text: str, start: int) -> str:
    """The text from ``start`` to the end of its clause, at most `NEAR` characters."""
    rest = text[start : start + NEAR]
    end = CLAUSE_END.search(rest)
    return rest[: end.start()] if end else rest


def default_claims(text: str) -> list[tuple[int, str]]:
    """(line, model) for every place ``text`` says which model is the default."""
    claims = []
    for found in re.finditer(rf"({MENTION.pattern})`?\s*\(default\)", text):
        claims.append((found.start(), _named(found.group(1))))
    for found in re.finditer(rf"({MENTION.pattern})\W*default model", text):
        claims.append((found.start(), _named(found.group(1))))
    for found in re.finditer(r"\bdefault(?:\s+model)?\s*(?::|=|\bis\b)", text):
        model = _first_model(_clause(text, found.end()))
        if model is not None:
            claims.append((found.start(), model))
    for found in re.finditer(r"from_pretrained\((?:\)|device=|dtype=)[^\n#]*#([^\n]*)", text):
        model = _first_model(found.group(1))
        if model is not None:
            claims.append((found.start(), model))
    return [(text.count("\n", 0, at) + 1, model) for at, model in claims]


def test_the_checker_reads_claims_both_ways():
    wrong = (
        f"| `{FALLBACK_MODEL}` (default) | ours |\n"
        "predictor = taptr.Predictor.from_pretrained()     # the bundled model\n"
        "--checkpoint X  checkpoint file (default: the bundled model)\n"
        "source: a file or name (None: the bundled default model).\n"
    )
    assert [model for _, model in default_claims(wrong)] == [FALLBACK_MODEL] * 4
    right = (
        f"| `{DEFAULT_MODEL}` (default) | the paper's |\n"
        "from_pretrained()  # the default model: the paper's weights, else the bundled one\n"
        f"(default: the paper's weights {DEFAULT_MODEL}; offline, the bundled {FALLBACK_MODEL})\n"
        "`--mode` | `first` (default) or `strided`, default small\n"
    )
    assert {model for _, model in default_claims(right)} == {DEFAULT_MODEL}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_no_page_names_another_default_model(page):
    if page.suffix not in (".md", ".py"):
        pytest.skip("not text")
    claims = default_claims(page.read_text())
    wrong = [(line, model) for line, model in claims if model != DEFAULT_MODEL]
    assert not wrong, (
        f"{page.relative_to(REPO)} calls another model the default (the code's is "
        f"{DEFAULT_MODEL}, else {FALLBACK_MODEL}): " + ", ".join(f"line {n}: {m}" for n, m in wrong)
    )


@pytest.mark.parametrize("name", STATING_PAGES)
def test_reader_pages_state_the_default_and_its_licence(name):
    text = (REPO / name).read_text()
    sentences = re.split(r"(?<=[.!?])\s+(?=[A-Z`*(])", " ".join(text.split()))
    stating = [s for s in sentences if re.search(rf"default\W.*{re.escape(DEFAULT_MODEL)}", s)]
    assert stating, f"{name} never says that {DEFAULT_MODEL} is the default model"
    assert any("non-commercial" in s for s in stating), (
        f"{name} names the default {DEFAULT_MODEL} without its licence (non-commercial)"
    )


@pytest.mark.parametrize("name", STATING_PAGES)
def test_reader_pages_state_the_fallback_with_the_default(name):
    text = " ".join((REPO / name).read_text().split())
    sentences = re.split(r"(?<=[.!?])\s+(?=[A-Z`*(])", text)
    stating = [
        i
        for i, s in enumerate(sentences)
        if re.search(rf"default\W.*{re.escape(DEFAULT_MODEL)}", s)
    ]
    # the fallback is said in the same sentence or the next one
    assert any(FALLBACK_MODEL in " ".join(sentences[i : i + 2]) for i in stating), (
        f"{name} states the default {DEFAULT_MODEL} without what runs when it cannot be had "
        f"({FALLBACK_MODEL})"
    )


def test_help_and_the_fallback_line_name_the_chain():
    from taptr.cli.common.model_options import CHECKPOINT_HELP
    from taptr.cli.main import build_parser
    from taptr.weights.registry import fallback_notice

    for model in (DEFAULT_MODEL, FALLBACK_MODEL):
        assert model in CHECKPOINT_HELP
    commands = build_parser()._subparsers._group_actions[0].choices
    defaults = {
        command: action.help
        for command, parser in commands.items()
        for action in parser._actions
        if "--checkpoint" in action.option_strings and "default" in (action.help or "")
    }
    assert {"track", "edit"} <= set(defaults)
    for command, text in defaults.items():
        assert DEFAULT_MODEL in text and FALLBACK_MODEL in text, f"taptr {command} --help"
    line = fallback_notice("offline")
    assert "\n" not in line and DEFAULT_MODEL in line and FALLBACK_MODEL in line

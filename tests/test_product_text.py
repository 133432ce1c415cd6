"""What the product says of itself: what things are and do, not which issue asked for them; the
stages numbered as ``iristac run`` runs them; every test a doc names exists; no pointer outside
the repository."""

from __future__ import annotations

import io
import re
import tokenize

from helpers import REPO
from pipeline.stages import STAGE_ORDER

PACKAGES = ("sim", "calibration", "pipeline", "data_schemas")
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".json", ".toml", ".txt"}
ISSUE = re.compile(r"\bissues?[ -]#?\d", re.IGNORECASE)


def product_files():
    """Every text file of the packages, README.md, pyproject.toml and docs/ (relative path, text)."""
    paths = [REPO / "README.md", REPO / "pyproject.toml"]
    for top in (*PACKAGES, "docs"):
        paths += sorted(p for p in (REPO / top).rglob("*") if p.suffix in TEXT_SUFFIXES and p.is_file())
    for p in paths:
        rel = p.relative_to(REPO).as_posix()
        yield rel, p.read_text(encoding="utf-8")


def test_the_product_does_not_cite_issue_numbers():
    hits = [f"{rel}:{i}: {line.strip()}" for rel, text in product_files()
            for i, line in enumerate(text.splitlines(), 1) if ISSUE.search(line)]
    assert hits == [], "say what the thing is or does, not which issue asked for it"


def test_test_comments_do_not_cite_issue_numbers():
    hits = []
    for path in sorted((REPO / "tests").rglob("*.py")):
        for tok in tokenize.generate_tokens(io.StringIO(path.read_text(encoding="utf-8")).readline):
            if tok.type == tokenize.COMMENT and ISSUE.search(tok.string):
                hits.append(f"{path.relative_to(REPO).as_posix()}:{tok.start[0]}: {tok.string}")
    assert hits == []


#: "Stage 2, calibrate", "stage 1: synthesize", "1. **synthesize**", "Calibration (stage 2)".
_NUMBERED = [re.compile(r"\bstage ([1-9])\W{0,3}(\w+)", re.IGNORECASE),
             re.compile(r"(?<![\d.])([1-9])\. \*\*(\w+)\*\*"),
             re.compile(r"#+ (\w+) \(stage ([1-9])\)", re.IGNORECASE)]
_HEADING_STAGE = {"calibration": "calibrate", "capture": "capture", "synthesis": "synthesize"}


def test_stage_numbers_follow_stage_order():
    wrong = []
    for rel, text in product_files():
        for i, line in enumerate(text.splitlines(), 1):
            for k, pattern in enumerate(_NUMBERED):
                for m in pattern.finditer(line):
                    number, name = (m.group(2), m.group(1)) if k == 2 else (m.group(1), m.group(2))
                    # a numbered list of stages names them in lower case ("1. **Capture**" is a step)
                    name = name if k == 1 else _HEADING_STAGE.get(name.lower(), name.lower())
                    if name in STAGE_ORDER and int(number) != STAGE_ORDER.index(name) + 1:
                        wrong.append(f"{rel}:{i}: {m.group(0)} ({name} is stage {STAGE_ORDER.index(name) + 1})")
    assert wrong == []


def test_the_stage_modules_number_themselves_by_stage_order():
    for n, name in enumerate(STAGE_ORDER, 1):
        doc = (REPO / "pipeline" / "stages" / f"{name}.py").read_text(encoding="utf-8")
        assert doc.startswith(f'"""Stage {n}, {name}:'), name


def test_every_test_path_a_doc_names_exists():
    named = {m.group(0).rstrip(".") for p in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
             for m in re.finditer(r"\btests/[\w/.-]*\w", p.read_text(encoding="utf-8"))}
    assert named, "the docs name tests"
    assert sorted(p for p in named if not (REPO / p).exists()) == []


def test_docs_point_inside_the_repository():
    outside = [f"{rel}:{i}" for rel, text in product_files()
               for i, line in enumerate(text.splitlines(), 1) if "DESIGN.md" in line]
    assert outside == [], "the design is docs/design.md"

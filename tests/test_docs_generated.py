"""The benchmark pages' figures are written by the benchmark scripts, never copied by hand.

A page under ``docs/benchmarks/`` may hold tables of figures only by including a fragment
that a script wrote (``--8<-- "benchmarks/generated/....md"``, pymdownx.snippets); a table
in the page's own text may hold words, not figures. Each included fragment names the
command that wrote it in its first lines (``Written by `python benchmarks/bench_....py ...```),
and that script exists and has the ``--markdown`` option. The checks are tried on pages
written for the purpose first, so that they are seen to fail where they should.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = DOCS / "benchmarks"
GENERATED = PAGES / "generated"

#: a snippet include line (pymdownx.snippets' default marker), and the file it names
INCLUDE = re.compile(r'^\s*-{1,}8<-{1,}\s+"([^"]+)"\s*$')
#: the command a fragment names in its first lines (``Written by `python benchmarks/...```,
#: ``Command: `...```), and its script
WRITTEN_BY = re.compile(r"`[^`\n]*\bpython\s+(benchmarks/[\w/]+\.py)\b[^`\n]*`")
#: a table's separator row: | --- | ---: | :---: |
SEPARATOR = re.compile(r"^\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")
#: a cell that is a figure: a number first (after emphasis, a sign or an approximation),
#: such as 125.3 s, **5.7x**, 1,655, 0 of 3,000, 99.97 %, ~40 %
FIGURE = re.compile(r"^[~≈<>+\-−]?\s*\d")


def _cells(line: str) -> list[str]:
    inner = line.strip()
    inner = inner[1:] if inner.startswith("|") else inner
    inner = inner[:-1] if inner.endswith("|") else inner
    return [c.strip().strip("*_ ").strip() for c in inner.split("|")]


def _without_code(text: str) -> list[str]:
    """The page's lines outside fenced code blocks (a table shown as code is not a table)."""
    lines, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(line)
    return lines


def hand_tables(text: str) -> list[str]:
    """The header rows of the tables in ``text``'s own Markdown that hold figures."""
    lines = _without_code(text)
    found = []
    for i in range(1, len(lines)):
        if not (SEPARATOR.match(lines[i]) and "|" in lines[i - 1]):
            continue
        body = []
        for line in lines[i + 1 :]:
            if "|" not in line or not line.strip():
                break
            body.append(line)
        if any(FIGURE.match(cell) for row in body for cell in _cells(row)):
            found.append(lines[i - 1].strip())
    return found


def includes(text: str) -> list[str]:
    """The files a page includes (paths as written, relative to ``docs/``)."""
    return [m.group(1) for line in _without_code(text) if (m := INCLUDE.match(line))]


def fragment_problem(path: Path, generated: Path = GENERATED, root: Path = ROOT) -> str | None:
    """Why an included fragment is not one a benchmark script wrote, or None."""
    if not path.is_file():
        return f"{path} does not exist"
    if generated.resolve() not in path.resolve().parents:
        return f"{path} is not under {generated}"
    head = "\n".join(path.read_text(encoding="utf-8").splitlines()[:10])
    m = WRITTEN_BY.search(head)
    if m is None:
        return f"{path} names no `python benchmarks/....py ...` command in its first lines"
    script = root / m.group(1)
    if not script.is_file() or "--markdown" not in script.read_text(encoding="utf-8"):
        return f"{path} names {m.group(1)}, which does not exist or has no --markdown option"
    return None


def page_problems(page: Path) -> list[str]:
    """Everything wrong with one benchmark page: hand-written tables of figures, included
    files that a script did not write."""
    text = page.read_text(encoding="utf-8")
    problems = [
        f"{page.name}: a table of figures written by hand (headed {row!r}); let the "
        "benchmark script write it (--markdown) and include the file"
        for row in hand_tables(text)
    ]
    for name in includes(text):
        why = fragment_problem(DOCS / name)
        if why:
            problems.append(f"{page.name}: {why}")
    return problems


def _pages() -> list[Path]:
    return sorted(p for p in PAGES.glob("*.md"))


# -- the checks, tried on pages written for the purpose -----------------------------------------
HAND_WRITTEN = """# A page

Some prose with a figure in it, 125 s, which this test leaves to review.

| command | before | after |
| --- | ---: | ---: |
| `vfm evaluate` | **160.7 s** | 46.0 s (3.5x) |
"""

WORDS_ONLY = """# A page

| page | script | what it measures |
| --- | --- | --- |
| [Speed](speed.md) | `benchmarks/bench_speed.py` | one online update |

```
| a | table | shown as code |
| --- | --- | --- |
| 1 | 2 | 3 |
```

--8<-- "benchmarks/generated/speed.md"
"""


def test_a_hand_written_table_of_figures_is_found() -> None:
    assert hand_tables(HAND_WRITTEN) == ["| command | before | after |"]
    # a figure anywhere in the body counts, not only in the last columns
    assert hand_tables("| a | b |\n| --- | --- |\n| x | y |\n| ~40 % | z |\n") == ["| a | b |"]


def test_tables_of_words_code_and_includes_are_not_hand_written_figures() -> None:
    assert hand_tables(WORDS_ONLY) == []
    assert includes(WORDS_ONLY) == ["benchmarks/generated/speed.md"]


def test_a_hand_written_page_fails_the_page_check(tmp_path: Path) -> None:
    page = tmp_path / "diary.md"
    page.write_text(HAND_WRITTEN + '\n--8<-- "benchmarks/generated/missing.md"\n')
    problems = page_problems(page)
    assert len(problems) == 2, problems
    assert "written by hand" in problems[0] and "does not exist" in problems[1]


def test_a_fragment_must_name_the_script_that_wrote_it(tmp_path: Path) -> None:
    fake = GENERATED / "speed.md"  # exists and was written by its script: accepted
    assert fragment_problem(fake) is None
    copied = tmp_path / "copied.md"
    copied.write_text("| a | b |\n| --- | --- |\n| 1 | 2 |\n")
    assert "is not under" in str(fragment_problem(copied))
    generated = tmp_path / "generated"  # a fragment under generated/ that names no command
    generated.mkdir()
    unnamed = generated / "unnamed.md"
    unnamed.write_text("Copied from a run.\n\n| a | b |\n| --- | --- |\n| 1 | 2 |\n")
    assert "names no" in str(fragment_problem(unnamed, generated))
    unnamed.write_text("Written by `python benchmarks/bench_nothing.py --markdown x`.\n")
    assert "does not exist" in str(fragment_problem(unnamed, generated))
    (tmp_path / "benchmarks").mkdir()  # a script without the option
    (tmp_path / "benchmarks" / "bench_nothing.py").write_text("print(1)\n")
    assert "no --markdown" in str(fragment_problem(unnamed, generated, tmp_path))
    (tmp_path / "benchmarks" / "bench_nothing.py").write_text("# --markdown PATH\n")
    assert fragment_problem(unnamed, generated, tmp_path) is None


# -- the documentation's own pages ---------------------------------------------------------------
@pytest.mark.parametrize("page", _pages(), ids=lambda p: p.name)
def test_benchmark_pages_show_only_figures_a_script_wrote(page: Path) -> None:
    assert page_problems(page) == []


def test_every_page_with_a_fragment_is_found() -> None:
    """The pages above are the ones there are (the glob did not come back empty), and the
    pages that show figures include at least one fragment."""
    pages = {p.name for p in _pages()}
    assert {"speed.md", "study.md", "service.md", "physics.md"} <= pages
    for name in ("speed.md", "study.md", "service.md", "physics.md"):
        assert includes((PAGES / name).read_text(encoding="utf-8")), name

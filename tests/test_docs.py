"""The README fits on a screen, every relative link in README.md and docs/*.md resolves (files and anchors), and
the commands they show quote their bracketed values (zsh)."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _prose(path: Path) -> str:
    """The page without its fenced code blocks (a link there is code, not a link)."""
    return re.sub(r"^```.*?^```", "", path.read_text(), flags=re.S | re.M)


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown page."""
    heads = re.findall(r"^#+\s+(.*?)\s*$", _prose(path), flags=re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in heads}


def test_readme_fits_on_a_screen():
    """A README for users (issue 52 §4): at most 120 lines, the quickstart before any result."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 120
    assert text.index("## Two commands") < text.index("## Results")


def test_ci_runs_exactly_the_readmes_test_command():
    """.ci/run's command is the README's second command, word for word, and every pytest option it passes comes from a
    plugin the test extras install (``-n``: pytest-xdist)."""
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    commands = [ln for ln in readme.splitlines() if ln.startswith("bash scripts/setup.sh && ")]
    assert commands[-1] == ci, (commands, ci)
    if " -n " in ci:
        assert '"pytest-xdist"' in (ROOT / "pyproject.toml").read_text()


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    bad = []
    for target in LINK.findall(_prose(page)):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.exists():
            bad.append(f"{target} (no {dest})")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target} (no heading #{anchor} in {dest.name})")
    assert not bad, f"{page.name}: " + "; ".join(bad)


def test_the_check_sees_links_and_anchors(tmp_path):
    (tmp_path / "a.md").write_text("# Top\n## Uncertainty (`b3dgs-eval`)\n[x](a.md#uncertainty-b3dgs-eval) [y](b.md)\n")
    assert LINK.findall(_prose(tmp_path / "a.md")) == ["a.md#uncertainty-b3dgs-eval", "b.md"]
    assert "uncertainty-b3dgs-eval" in _anchors(tmp_path / "a.md")


_COMMAND = re.compile(r"^\s*(?:[A-Z_]+=\S+\s+)*(?:b3dgs-[a-z]+|python -m (?:bench|b3dgs)\S*)(?:\s|$)")
_TOKEN = re.compile(r"(?:'[^']*'|\"[^\"]*\"|\S)+")


def _commands(text: str):
    """(line, command) of every shell command a page shows: fenced code-block lines and inline code spans."""
    block = False
    for i, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            block = not block
        elif block:
            if _COMMAND.match(line.split("  #")[0]):
                yield i, line.split("  #")[0]
        else:
            yield from ((i, span) for span in re.findall(r"`([^`]+)`", line) if _COMMAND.match(span))


def _unquoted_brackets(command: str) -> list[str]:
    """The words of ``command`` with a ``[`` outside quotes (zsh: "no matches found"; bash globs them), leaving out
    usage placeholders such as ``[--seeds N]``."""
    return [t for t in _TOKEN.findall(command) if not t.startswith("[")
            and "[" in re.sub(r"'[^']*'|\"[^\"]*\"", "", t)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_commands_quote_bracketed_values(page):
    """A command copied from the docs runs in zsh as in bash: `'uq=[native,proxy]'`, not `uq=[native,proxy]`."""
    bad = [f"line {i}: {w}" for i, c in _commands(page.read_text()) for w in _unquoted_brackets(c)]
    assert not bad, f"{page.name}: quote these words: " + "; ".join(bad)


def test_the_quoting_check_sees_unquoted_brackets():
    text = "run `b3dgs-eval run=R uq=[native]` or\n```\nb3dgs-train 'posterior=[niw]' x=\"[a]\"  # uq=[x]\n" \
           "python -m bench.train [--seeds N] seeds=[0],[1]\n```\n"
    assert [(i, w) for i, c in _commands(text) for w in _unquoted_brackets(c)] == \
        [(1, "uq=[native]"), (4, "seeds=[0],[1]")]

"""The documentation's own checks: relative links resolve, CITATION.cff is valid, the API
reference's landing page covers the modules it builds.

The API reference itself is built (and fails on any pdoc warning) by `.ci/run`, not here: it
imports every public module, which the rest of the suite already does.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path
from urllib.parse import unquote

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: the pages whose links are checked
PAGES = sorted([ROOT / "README.md", ROOT / "CHANGELOG.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "docs").glob("*/*.md")])

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1", re.S)
_INLINE = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+[\"'(][^)]*)?\)")
_REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$", re.M)
_HTML = re.compile(r"""<(?:a|img)\b[^>]*?\b(?:href|src)\s*=\s*["']([^"']+)["']""", re.I)


def relative_links(text: str) -> list[str]:
    """The relative link targets of a Markdown text, outside code, without their anchors."""
    text = _CODE_SPAN.sub("", _FENCE.sub("", text))
    targets = _INLINE.findall(text) + _REFERENCE.findall(text) + _HTML.findall(text)
    out = []
    for target in targets:
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith(("#", "//")):
            continue  # a URL (http:, mailto:, ...) or an anchor on the same page
        path = unquote(target.split("#", 1)[0].split("?", 1)[0])
        if path:
            out.append(path)
    return out


def test_link_extraction():
    text = (
        "[a](a.md) [b](docs/b.md#part) ![img](img/x.png \"title\") [web](https://x.org/y.md) [same](#here)\n"
        "`[not](code.md)` and\n```\n[not](fenced.md)\n```\n[ref]: ref.md\n<img src=\"html.png\"> [sp](my%20file.md)\n"
    )
    assert relative_links(text) == ["a.md", "docs/b.md", "img/x.png", "my file.md", "ref.md", "html.png"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path):
    broken = [t for t in relative_links(page.read_text(encoding="utf-8")) if not (page.parent / t).exists()]
    assert not broken, f"{page.relative_to(ROOT)} links to missing files: {broken}"


def test_citation_cff_loads_with_the_required_keys():
    yaml = pytest.importorskip("yaml")
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert cff["cff-version"] == "1.2.0"
    for key in ("message", "title", "authors"):
        assert cff.get(key), f"CITATION.cff lacks {key!r}"

    def check_authors(authors, where):
        assert isinstance(authors, list) and authors, f"{where}: authors must be a non-empty list"
        for person in authors:
            assert person.get("name") or person.get("family-names"), f"{where}: an author without a name: {person}"

    check_authors(cff["authors"], "CITATION.cff")
    import tomllib

    version = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    assert str(cff.get("version")) == version, "CITATION.cff's version differs from pyproject.toml's"
    works = [cff["preferred-citation"]] if "preferred-citation" in cff else []
    works += cff.get("references", [])
    titles = " | ".join(w["title"] for w in works)
    assert "PIPPS" in titles and "Total stochastic gradient" in titles, titles
    for work in works:
        for key in ("type", "title", "authors"):
            assert work.get(key), f"CITATION.cff: {work.get('title')!r} lacks {key!r}"
        check_authors(work["authors"], work["title"])


def test_api_landing_page_lists_every_module_the_reference_builds():
    tree = ast.parse((ROOT / "docs" / "api" / "build.py").read_text(encoding="utf-8"))
    public = next(
        ast.literal_eval(node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "PUBLIC" for t in node.targets)
    )
    landing = (ROOT / "docs" / "api" / "index.md").read_text(encoding="utf-8")
    missing = [m for m in public if f"| `{m}` |" not in landing]
    assert not missing, f"docs/api/index.md does not describe {missing}"
    for module in public:
        assert (ROOT / (module.replace(".", "/"))).is_dir() or (ROOT / (module.replace(".", "/") + ".py")).is_file()


def _readme_python_blocks() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"^```python\n(.*?)^```", text, re.S | re.M)


def test_the_readme_library_example_runs_as_written(capsys):
    """The README's library example, executed verbatim: a TP gradient of a policy on a GP fitted to
    one random trial. It must print a finite objective and a nonzero, finite gradient norm."""
    blocks = _readme_python_blocks()
    assert len(blocks) == 1, "the README has one library example"
    exec(compile(blocks[0], "README.md", "exec"), {"__name__": "readme_example"})
    line = capsys.readouterr().out.strip().splitlines()[-1]
    match = re.fullmatch(r"J = (\S+); \|∇J\| = (\S+)", line)
    assert match, line
    value, norm = float(match.group(1)), float(match.group(2))
    assert 0.0 <= value <= 30.0 and 0.0 < norm < float("inf")

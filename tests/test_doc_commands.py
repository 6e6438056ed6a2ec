"""Every command the documentation shows is one a reader can run: each `pipps …` line parses with the
CLI's own parser, each `python experiments/….py` script exists, and every committed input it names
(`results/…`, brace and glob patterns expanded as bash would) exists.

The check reads the pages' code spans and code blocks; fragments (a bare subcommand, alternatives
written with `|` or `/`, `[optional]` parts, `…`, upper-case placeholders such as FILES or X.h5)
are mentions, not commands, and are left out. docs/reliability.md's table shows invalid input on
purpose; its commands are checked for their paths only. Output paths (`--out`, `--svg`, …) need not
exist, nor do paths under a user's own `runs/`.
"""

from __future__ import annotations

import glob
import re
import shlex
from pathlib import Path

import pytest

from pipps.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md"), ROOT / "results/README.md",
                ROOT / "experiments/README.md"])
#: pages whose commands are wrong on purpose (the error each gives is the point)
INVALID_ON_PURPOSE = {ROOT / "docs/reliability.md"}
#: options whose value is written, not read
OUTPUTS = {"--out", "--svg", "--rrd", "--png", "-o"}
_PREFIX = re.compile(r"^(?:(?:JAX_PLATFORMS|PYTHONPATH|XLA_FLAGS|CELL_SECONDS)=\S+\s+|taskset -c \S+\s+|nice(?: -n \S+)?\s+)+")
_COMMAND = re.compile(r"^(?:pipps (?:table|plot|resimulate|run|sweep|study|bench|rollout)\b|python3? experiments/\S+\.py\b)")


def _blocks(lines: list[str]) -> list[str]:
    """The commands of a code block: one per line, a trailing backslash joining the next."""
    out, cur = [], ""
    for line in lines:
        s = line.strip()
        if s.endswith("\\"):
            cur += s[:-1].rstrip() + " "
            continue
        if cur or s:
            out.append(cur + s)
        cur = ""
    return out + ([cur] if cur else [])


def snippets(text: str) -> list[str]:
    """Fenced and indented code blocks (line by line) and inline code spans (joined over line breaks)."""
    out, prose, lines, i, prev_blank = [], [], text.split("\n"), 0, True
    while i < len(lines):
        line = lines[i]
        if line.strip().startswith("```"):
            j = i + 1
            while j < len(lines) and not lines[j].strip().startswith("```"):
                j += 1
            out += _blocks(lines[i + 1:j])
            i, prev_blank = j + 1, True
            continue
        if line.startswith("    ") and prev_blank and not line.lstrip().startswith(("-", "|", "*")):
            j = i
            while j < len(lines) and (lines[j].startswith("    ") or not lines[j].strip()):
                j += 1
            out += _blocks(lines[i:j])
            i, prev_blank = j, True
            continue
        prose.append(line)
        prev_blank = not line.strip()
        i += 1
    out += [re.sub(r"\s*\n\s*", " ", m) for m in re.findall(r"`([^`]+)`", "\n".join(prose))]
    return out


def expand_braces(token: str) -> list[str]:
    """bash's brace expansion: `{a,b}` and `{0..9}`, nested left to right."""
    m = re.search(r"\{([^{}]*)\}", token)
    if not m:
        return [token]
    inner = m.group(1)
    if r := re.fullmatch(r"(-?\d+)\.\.(-?\d+)", inner):
        alternatives = [str(v) for v in range(int(r.group(1)), int(r.group(2)) + 1)]
    elif "," in inner:
        alternatives = inner.split(",")
    else:
        return [token]
    return [t for a in alternatives for t in expand_braces(token[:m.start()] + a + token[m.end():])]


def is_fragment(command: str, tokens: list[str]) -> bool:
    """A mention rather than a command: a bare subcommand or one option named with its value
    (`pipps sweep --batched`, `pipps sweep --jobs auto`, `pipps study variance`), alternatives,
    optional parts or placeholders."""
    rest = tokens[3:] if tokens[:2] in (["pipps", "study"], ["pipps", "bench"]) else tokens[2:]
    return (tokens[0] == "pipps" and (not rest or (rest[0].startswith("-") and len(rest) <= 2))
            or any(t in {"|", "/"} or "|" in t or t.startswith("[") for t in tokens)
            or any(re.fullmatch(r"[A-Z][A-Z_0-9]*(\.h5)?", t) or re.search(r"(^|/)[A-Z][A-Z_]*\.h5$", t)
                   for t in tokens))


def doc_commands():
    for page in PAGES:
        for snippet in snippets(page.read_text(encoding="utf-8")):
            command = re.sub(r"\s+#.*$", "", _PREFIX.sub("", snippet.strip()))
            if _COMMAND.match(command):
                yield page, command


def problems(page: Path, command: str, parser) -> list[str]:
    if "…" in command or "..." in command or "<" in command:
        return []  # elided or a placeholder
    try:
        tokens = shlex.split(command)
    except ValueError as exc:
        return [f"cannot be split as a shell command ({exc})"]
    if is_fragment(command, tokens):
        return []
    found, argv, previous = [], [], None
    for token in tokens:
        for word in expand_braces(token):
            if previous not in OUTPUTS and word.startswith(("results/", "experiments/", "benchmarks/")):
                if any(ch in word for ch in "*?["):
                    matches = sorted(glob.glob(str(ROOT / word)))
                    found += [] if matches else [f"{word} matches no file"]
                elif not (ROOT / word).exists():
                    found.append(f"{word} does not exist")
            argv.append(word)
        previous = token
    if argv[0] == "pipps" and page not in INVALID_ON_PURPOSE:
        try:
            parser.parse_args(argv[1:])
        except SystemExit as exc:
            if exc.code:  # --help exits 0
                found.append("the CLI's parser refuses it")
    return found


def test_the_extraction_reads_spans_blocks_and_continuations():
    text = ("Run `pipps table results/thesis\n--table 4.1` or\n\n    pipps resimulate results/thesis \\\n"
            "        --fresh 300\n\n```\npipps plot runs --figure cells --out a.rrd\n```\n")
    assert snippets(text) == ["pipps resimulate results/thesis --fresh 300",
                              "pipps plot runs --figure cells --out a.rrd", "pipps table results/thesis --table 4.1"]
    assert expand_braces("a_{tp,pilco}_s{0..2}.h5") == ["a_tp_s0.h5", "a_tp_s1.h5", "a_tp_s2.h5",
                                                         "a_pilco_s0.h5", "a_pilco_s1.h5", "a_pilco_s2.h5"]


def test_the_check_can_fail(capsys):
    parser = build_parser()
    assert problems(ROOT / "README.md", "pipps table results/no-such-folder --table 4.1", parser)
    assert problems(ROOT / "README.md", "pipps sweep --methods tp --set x=1 --dry-run", parser)  # --table required
    capsys.readouterr()
    assert not problems(ROOT / "README.md", "pipps table results/thesis --table 4.1 --per-seed", parser)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_documented_command_can_run_as_written(page: Path, capsys):
    parser = build_parser()
    bad = {c: p for pg, c in doc_commands() if pg == page and (p := problems(pg, c, parser))}
    capsys.readouterr()  # argparse's usage lines
    assert not bad, f"{page.relative_to(ROOT)}: " + "; ".join(f"`{c}`: {', '.join(p)}" for c, p in bad.items())

"""Regenerate the tables embedded in docs/results.md between ``<!-- pipps:NAME -->`` and
``<!-- /pipps -->`` markers from ``pipps table results/thesis`` (run from the repository root), so
the page shows exactly what the command prints:

    python experiments/results_tables.py

A maintainer's tool that rewrites docs/results.md in place, but only the blocks between those
markers: the rest of the page is kept as it is. A page with none of the markers is refused (one
line) before any table is computed. The new page is written to a temporary file beside it and
moved into place in one step, so the page is never seen half-written.
"""
import os, re, subprocess, sys

PAGE = "docs/results.md"

def refuse(line):
    print(f"results_tables.py: error: {line}", file=sys.stderr)
    sys.exit(2)

def read_page():
    """The page's text; exits with one line if it cannot be read or holds no ``<!-- pipps:NAME -->`` marker."""
    try:
        text = open(PAGE).read()
    except OSError as err:
        refuse(f"cannot read {PAGE}: {err.strerror or err}")
    if not re.search(r"<!-- pipps:[^ ]+ -->", text):
        refuse(f"{PAGE} has no <!-- pipps:NAME --> markers; this tool rewrites only the blocks between them")
    return text

def write_page(text):
    """Replace the page whole: a temporary file beside it, then ``os.replace``."""
    tmp = os.path.join(os.path.dirname(PAGE), f".{os.path.basename(PAGE)}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, PAGE)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)

read_page()  # before any table is computed

def table_output(*args):
    return subprocess.run(["pipps", "table", "results/thesis", *args], capture_output=True, text=True,
                          env={**__import__("os").environ, "JAX_PLATFORMS": "cpu"}).stdout.split("\n")

def block(lines, start):
    i = next(i for i, l in enumerate(lines) if l.startswith(start))
    out, j = [], i + 2
    while j < len(lines) and lines[j].startswith("|"):
        out.append(lines[j]); j += 1
    return out

t41 = table_output("--table", "4.1")
t41rp = table_output("--table", "4.1", "--compare", "tp,rp")
every = block(t41, "**Table 4.1 — cart-pole swing-up, Angle Cost**, every reading")
head, rows = every[:2], every[2:]
blocks = {
    "t41-tp-pilco": head + [r for r in rows if "| TP |" in r or "| PILCO |" in r],
    "t41-diff": block(t41, "**Table 4.1 — cart-pole swing-up, Angle Cost**, TP − PILCO"),
    "t41-k1": head + [r for r in rows if r.startswith("| k = 1 |")],
    "t41-diff-rp": block(t41rp, "**Table 4.1 — cart-pole swing-up, Angle Cost**, TP − RP"),
}
for name in ("4.2", "4.3", "4.4", "del"):
    out = table_output("--table", name)
    try:
        blocks["t" + name.replace(".", "")] = [l for l in out if l.strip()][:200]
    except StopIteration:
        pass
s = read_page()  # again: the page may have been edited while the tables ran
for name, lines in blocks.items():
    pat = re.compile(rf"(<!-- pipps:{name} -->\n).*?(\n<!-- /pipps -->)", re.S)
    if pat.search(s):
        s = pat.sub(lambda m: m.group(1) + "\n".join(lines) + m.group(2), s)
write_page(s)
print("filled", [n for n in blocks if f"<!-- pipps:{n} -->" in s])

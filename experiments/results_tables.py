"""Regenerate the tables embedded in docs/results.md between ``<!-- pipps:NAME -->`` and
``<!-- /pipps -->`` markers from ``pipps table results/thesis`` (run from the repository root), so
the page shows exactly what the command prints:

    python experiments/results_tables.py
"""
import re, subprocess, sys

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
s = open("docs/results.md").read()
for name, lines in blocks.items():
    pat = re.compile(rf"(<!-- pipps:{name} -->\n).*?(\n<!-- /pipps -->)", re.S)
    if pat.search(s):
        s = pat.sub(lambda m: m.group(1) + "\n".join(lines) + m.group(2), s)
open("docs/results.md", "w").write(s)
print("filled", [n for n in blocks if f"<!-- pipps:{n} -->" in s])

"""Regenerate the tables embedded in docs/results.md and README.md between ``<!-- pipps:NAME -->`` and
``<!-- /pipps -->`` markers from ``pipps table`` on the committed results (run from the repository
root), so the pages show exactly what the command prints:

    python experiments/results_tables.py

``glance`` (docs/results.md, "At a glance") and ``readme`` (README.md, a subset of its rows) gather the
"every reading" rows of Tables 4.1–4.4, the Gaussian-shaping rows of Table 4.3 and the PILCO rows
with the policy-input noise term (``results/pilco-noise``, read with ``--by pilco_policy_noise``)
into one table with the same columns; the other blocks are ``pipps table results/thesis`` output
as printed.

A maintainer's tool that rewrites the pages in place, but only the blocks between those markers:
the rest of each page is kept as it is. docs/results.md without any of the markers is refused (one
line) before any table is computed; README.md is rewritten only where it has markers. Each new page
is written to a temporary file beside it and moved into place in one step, so a page is never seen
half-written.
"""
import os, re, subprocess, sys

PAGE = "docs/results.md"
README = "README.md"

def refuse(line):
    print(f"results_tables.py: error: {line}", file=sys.stderr)
    sys.exit(2)

def read_page(page=PAGE):
    """The page's text; exits with one line if it cannot be read or holds no ``<!-- pipps:NAME -->`` marker."""
    try:
        text = open(page).read()
    except OSError as err:
        refuse(f"cannot read {page}: {err.strerror or err}")
    if not re.search(r"<!-- pipps:[^ ]+ -->", text):
        refuse(f"{page} has no <!-- pipps:NAME --> markers; this tool rewrites only the blocks between them")
    return text

def write_page(text, page=PAGE):
    """Replace the page whole: a temporary file beside it, then ``os.replace``."""
    tmp = os.path.join(os.path.dirname(page), f".{os.path.basename(page)}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, page)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)

read_page()  # before any table is computed

def table_output(*args, folders=("results/thesis",)):
    return subprocess.run(["pipps", "table", *folders, *args], capture_output=True, text=True,
                          env={**os.environ, "JAX_PLATFORMS": "cpu"}).stdout.split("\n")

def block(lines, start):
    i = next(i for i, l in enumerate(lines) if l.startswith(start))
    out, j = [], i + 2
    while j < len(lines) and lines[j].startswith("|"):
        out.append(lines[j]); j += 1
    return out

def cells(line):
    return [c.strip() for c in line.strip().strip("|").split("|")]

GLANCE_READINGS = ("per trial, return", "per seed, mean return", "final system trial, return",
                   "per trial, physical", "per seed, physical", "final system trial, physical")

def every_reading_rows(lines, prefix, method_label=None, keep=lambda row: True):
    """The rows of the first "every reading" block in ``lines`` as dicts keyed by column name, the cell
    named ``prefix`` + the table's row; a ``--by`` block's value column picks ``method_label`` rows
    (the value ``True``). [] where there is no such block."""
    try:
        i = next(i for i, l in enumerate(lines) if ", every reading [" in l)
    except StopIteration:
        return []
    head = [h.strip("*") for h in cells(lines[i + 2])]
    out = []
    for line in lines[i + 4:]:
        if not line.startswith("|"):
            break
        row = dict(zip(head, cells(line)))
        if len(head) > 4 and head[2] not in ("seeds",):  # a --by block: | row | method | VALUE | seeds | ...
            if row[head[2]] != "True":
                continue
            row["method"] = method_label
        if keep(row):
            row["cell"] = prefix + row[head[0]]
            out.append(row)
    return out

def outside(thesis, rate):
    """Whether the thesis' value lies outside our interval ("0.49 [0.23, 0.77]")."""
    m = re.search(r"\[([-0-9.]+), ([-0-9.]+)\]", rate or "")
    return bool(m) and thesis not in ("–", "") and not float(m[1]) <= float(thesis) <= float(m[2])

def glance_table(rows):
    """One table of ``rows``; `!` after the thesis' value where it lies outside the headline's interval
    (per trial by the return, or physically where a task has no threshold)."""
    rows = [dict(r) for r in rows]
    for r in rows:
        headline = r.get(GLANCE_READINGS[0], "–")
        headline = r.get(GLANCE_READINGS[3], "–") if headline == "–" else headline
        if outside(r["thesis"], headline):
            r["thesis"] += " !"
    head = ["cell", "method", "seeds", "thesis", *GLANCE_READINGS]
    lines = ["| " + " | ".join(("**" + h + "**") if h == GLANCE_READINGS[0] else h for h in head) + " |",
             "|---" * len(head) + "|"]
    lines += ["| " + " | ".join(r.get(h, "–") for h in head) + " |" for r in rows]
    return lines

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
outs = {name: table_output("--table", name) for name in ("4.2", "4.3", "4.4", "del")}
for name, out in outs.items():
    blocks["t" + name.replace(".", "")] = [l for l in out if l.strip()][:200]
try:
    blocks["t42-every"] = block(outs["4.2"], "**Table 4.2 — cart-pole swing-up, Tip Cost**, every reading")
except StopIteration:  # no Table 4.2 results
    pass
TERM = "PILCO + policy-input noise term"
glance = (every_reading_rows(t41, "Table 4.1, ")
          + every_reading_rows(outs["4.2"], "Table 4.2, Tip Cost, ")
          + every_reading_rows(outs["4.3"], "Table 4.3, ", keep=lambda r: r["method"] in ("GTP", "GLR"))
          + every_reading_rows(outs["4.4"], "Table 4.4, ")
          + every_reading_rows(outs["del"], "Cart-pole balancing, ")
          + every_reading_rows(table_output("--table", "4.1", "--by", "pilco_policy_noise",
                                            folders=("results/pilco-noise", "results/thesis")), "Table 4.1, ", TERM)
          + every_reading_rows(table_output("--table", "4.2", "--by", "pilco_policy_noise",
                                            folders=("results/pilco-noise", "results/thesis")), "Table 4.2, Tip Cost, ", TERM))
README_METHODS = ("TP", "PILCO", "RP", "GTP", TERM)
if glance:
    blocks["glance"] = glance_table(glance)
    # the README's table: the thesis' Tables 4.1-4.4 (DEL on balancing is a figure there, not a table)
    blocks["readme"] = glance_table([r for r in glance if r["method"] in README_METHODS
                                     and not (r["method"] == "RP" and "k = 1" not in r["cell"])
                                     and not r["cell"].startswith("Cart-pole balancing")])
def coverage_blocks():
    """Every distinct cell of Tables 4.1–4.4 (a cell of Table 4.3 that is also one of Table 4.1 or 4.2
    once), its thesis value and every reading of our runs, or "no runs"; and the count of cells with
    runs by their number of seeds, for the README."""
    from pipps.experiments.methods import METHODS
    from pipps.reporting.tables import TABLES

    outputs = {"4.1": t41, **{n: outs[n] for n in ("4.2", "4.3", "4.4")}}
    found = {}
    for name, out in outputs.items():
        for r in every_reading_rows(out, ""):
            found[(name, r["cell"], r["method"])] = r
    cells, where = {}, {}
    for name in ("4.1", "4.2", "4.3", "4.4"):
        t = TABLES[name]
        for c in t.cells:
            v = dict(c.values)
            key = (t.task, v.get("cost", "default"), v.get("k", 1.0), c.method)
            cells.setdefault(key, (name, c))
            where.setdefault(key, []).append(name)
    head = ["cell", "method", "seeds", "thesis", *GLANCE_READINGS]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    counts = {"10+": 0, "5-9": 0, "1-4": 0, "none": 0}
    for key, (name, c) in cells.items():
        label = METHODS[c.method].label
        row = next((found[(n, c.row, label)] for n in where[key] if (n, c.row, label) in found), None)
        tables = " and ".join(f"Table {n}" for n in where[key])
        thesis = f"{c.thesis:.2f}"
        if row is None:
            counts["none"] += 1
            lines.append(f"| {tables}, {c.row} | {label} | 0 | {thesis} | no runs |" + " |" * (len(GLANCE_READINGS) - 1))
            continue
        seeds = int(row.get("seeds", "0") or 0)
        counts["10+" if seeds >= 10 else "5-9" if seeds >= 5 else "1-4"] += 1
        headline = row.get(GLANCE_READINGS[0], "–")
        headline = row.get(GLANCE_READINGS[3], "–") if headline == "–" else headline
        mark = " !" if outside(thesis, headline) else ""
        lines.append(f"| {tables}, {c.row} | {label} | {seeds} | {thesis}{mark} | "
                     + " | ".join(row.get(h, "–") for h in GLANCE_READINGS) + " |")
    total = len(cells)
    have = total - counts["none"]
    summary = (f"{have} of the {total} distinct cells of Tables 4.1–4.4 have runs: {counts['10+']} at 10 or more seeds, "
               f"{counts['5-9']} at 5–9, {counts['1-4']} at 1–4; {counts['none']} have none yet "
               "(docs/results.md, \"Every cell\", lists them all).")
    return lines, [summary]


blocks["coverage"], blocks["coverage-count"] = coverage_blocks()
filled = []
for page in (PAGE, README):
    if page == README and not (os.path.exists(page) and "<!-- pipps:" in open(page).read()):
        continue
    s = read_page(page)  # again: the page may have been edited while the tables ran
    for name, lines in blocks.items():
        # the block's old lines, if any, up to the nearest end marker (an empty block matches too)
        pat = re.compile(rf"(<!-- pipps:{name} -->\n)(?:.*?\n)??(<!-- /pipps -->)", re.S)
        if pat.search(s):
            s = pat.sub(lambda m: m.group(1) + "".join(line + "\n" for line in lines) + m.group(2), s)
            filled.append(name)
    write_page(s, page)
print("filled", filled)

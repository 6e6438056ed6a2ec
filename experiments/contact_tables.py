"""Regenerate the tables of docs/contact.md from the committed contact studies (results/contact/*.json),
between ``<!-- contact:NAME -->`` and ``<!-- /contact -->`` markers, so the page shows exactly what
``pipps study contact NAME --full`` printed:

    python experiments/contact_tables.py

``NAME`` is a study (its verdicts and its TP-against-AoBG rows, as ``pipps study contact`` prints
them) or ``tension`` (every study's TP-against-AoBG rows in one table). Only the blocks between the
markers change; the page is replaced whole (a temporary file, then ``os.replace``).
"""

import os
import re
import sys
from pathlib import Path

from pipps.studies.contact import read_study
from pipps.studies.contact_figures import verdict_table

PAGE = Path("docs/contact.md")
RESULTS = Path("results/contact")


def _f(v):
    return "—" if v is None else f"{v:.3g}"


def tension(results) -> str:
    lines = ["| system | estimator | ‖bias‖ | max \\|z\\| | variance (per sample) | MSE | weight on LR (TP: k_LR, AoBG: 1 − α) | file |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        for t in r.tables.get("tension", []):
            lines.append(f"| {t['system']} | {t['estimator']} | {_f(t['bias_norm'])} | {_f(t['max_z'])} | {_f(t['variance'])} | "
                         f"{_f(t['mse'])} | {_f(t['weight_on_lr'])} | `{name}.json` |")
    return "\n".join(lines)


def main() -> int:
    text = PAGE.read_text(encoding="utf-8")
    results = {p.stem: read_study(p) for p in sorted(RESULTS.glob("*.json"))}

    def fill(m):
        name = m.group(1)
        if name == "tension":
            body = tension(results)
        elif name in results:
            r = results[name]
            body = (verdict_table(r) + f"\n\n`{name}.json`: code {r.versions.get('code')}, jax {r.versions.get('jax')}, "
                    f"{r.settings.get('preset')} settings, seed {r.settings.get('seed', 0)}")
        else:
            print(f"contact_tables.py: no results/contact/{name}.json; block left as it is", file=sys.stderr)
            return m.group(0)
        return f"<!-- contact:{name} -->\n{body}\n<!-- /contact -->"

    new = re.sub(r"<!-- contact:([a-z0-9_]+) -->\n.*?<!-- /contact -->", fill, text, flags=re.S)
    tmp = PAGE.with_name(f".{PAGE.name}.tmp-{os.getpid()}")
    tmp.write_text(new, encoding="utf-8")
    os.replace(tmp, PAGE)
    return 0


if __name__ == "__main__":
    sys.exit(main())

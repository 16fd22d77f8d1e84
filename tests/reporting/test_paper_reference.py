"""The paper's Table 2 beside ours (issue 45): a reference block in our object columns, never bold, with the
paper's numbers as printed in its Table 2."""
from __future__ import annotations

import pandas as pd

from tasks.core.tables import markdown_table
from tasks.reporting.paper_reference import PAPER_LABEL, TABLE1, table1_rows
from tasks.reporting.report_tables import TABLE2, paper_layout, with_paper_rows


def test_table2_gets_the_papers_rows_in_our_object_order_never_bold():
    df = pd.DataFrame([{"object": "clay", "seed": 0, "variant": v, "bdc_t": x, "bdc_s": x, "sdc": x, "miou": x}
                       for v, x in (("full", 0.5), ("no_dirichlet", 0.4))] +
                      [{"object": "can", "seed": 0, "variant": v, "bdc_t": x, "bdc_s": x, "sdc": x, "miou": x}
                       for v, x in (("full", 0.6), ("no_dirichlet", 0.7))])
    labels = {"full": "Full", "no_dirichlet": "w/o Dirichlet"}
    title, header, rows, best = with_paper_rows("T2", *paper_layout(df, TABLE2, ["clay", "can"], labels),
                                                ["clay", "can"])
    assert header == ["Method", "Metric", "clay", "can", "Avg."]
    paper = rows[8:]
    assert len(paper) == 8 and all(r[0].startswith(PAPER_LABEL) for r in paper)
    assert not any(any(b) for b in best[8:]) and any(any(b) for b in best[:8])
    # the paper's Table 2: w/o Dirichlet BDC-T clay 0.73, can 0.85, Avg. 0.764; full mIoU clay 0.65, can 0.70, 0.669
    assert paper[0] == [f"{PAPER_LABEL}: VirSqueezer w/o Dirichlet Boundary Constraint", "BDC-T", "0.730", "0.850",
                        "0.764"]
    assert paper[-1] == [f"{PAPER_LABEL}: Full VirSqueezer", "mIoU", "0.650", "0.700", "0.669"]
    md = markdown_table(header, rows, best)
    assert "**0.730**" not in md and "paper (their metric definitions are not published)" in md


def test_table1_reference_rows_fill_only_the_columns_the_paper_gives():
    rows, best = table1_rows(["temporal_flicker", "physical_commonsense", "imaging_quality_musiq"], 1)
    ours = next(r for r in rows if r[0].endswith("VirSqueezer (Ours)"))
    assert ours[1:] == ["-", "0.368", "0.596", "3.9 / 4.1 / 4.2"]
    assert len(rows) == len(TABLE1) and not any(any(b) for b in best)

"""The run report: tables in the paper's layouts, plots and videos (markdown + self-contained HTML)."""

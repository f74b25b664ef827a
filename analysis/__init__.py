"""Analysis of finished run folders: tables, conclusions, collapse counts, figures and
aggregate statistics (``report.py``)."""

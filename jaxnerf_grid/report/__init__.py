"""What a run shows a person: report.md, report.html, the live progress page."""

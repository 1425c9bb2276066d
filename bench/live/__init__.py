"""Live operation (issue 48): watch a run in Foxglove while it runs (`bench run --live`, node.py) and
inject a fault while it runs (`bench inject`, inject_cli.py; the live view's service). docs/live.md."""

"""The bench's message contract, published and checked (issue 25).

`table.py` says which message goes on which key and who publishes and reads it; `export.py` writes
the JSON Schemas, that table and the protocol document (`bench contract export DIR`); `check.py`
runs the plant and estimator against an outside node and judges what it published
(`bench contract check controller`); `cli.py` adds the two commands. docs/contract.md is the guide.
"""

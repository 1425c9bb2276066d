"""The bench's message contract, published (issue 25); checked by bench/contract_check/.

`table.py` says which message goes on which key and who publishes and reads it; `fields.py` what
every field means (description, unit, frame, allowed values); `document.py` builds contract.json,
every number and meaning as data, for `bench contract export` and for each run (beside
scenario.json); `export.py` writes the JSON Schemas (every field described), that table, the
protocol document and contract.json (`bench contract export DIR`). docs/contract.md is the guide.
"""

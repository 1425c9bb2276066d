"""`bench contract check`: the bench run against an outside part and judged by the contract (issue 25).

`check.py` runs the plant and estimator against an outside controller and judges what it published
(`bench contract check controller`); `board_check.py` with `board_flight.py`, `board_run.py` and
`board_throughout.py` does the same for an outside magnetorquer board on the CAN bus (`bench
contract check board`); `probe.py` and `late_arrivals.py` are their pieces. It sits above the
launcher, which it starts; the contract itself (bench/contract/) sits below it. `cli.py` adds
`bench contract export` and `bench contract check`. docs/contract.md is the guide.
"""

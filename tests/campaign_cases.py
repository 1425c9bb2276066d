"""Case functions for the campaign tests (spec `mode = "campaign_cases:NAME"`): the in-process
run, made to raise, hang or take a while on chosen seeds."""
import time

from bench.sim import campaign_case as _run_in_process


def flaky_case(scenario):
    if scenario.run.seed == 2:
        raise RuntimeError("injected failure for seed 2")
    if scenario.run.seed == 3:
        time.sleep(120)                 # far past the spec's case_timeout_s
    return _run_in_process(scenario)


def slow_case(scenario):
    time.sleep(0.4)                     # long enough to kill the campaign halfway
    return _run_in_process(scenario)


def sleepy_case(scenario):
    time.sleep(300)                     # a case still running when the campaign is killed
    return _run_in_process(scenario)

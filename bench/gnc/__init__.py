"""Pure GNC algorithms: no Zenoh, no scenario files, no processes.

Plant, estimator, controller, planner and studies all import from here; nothing here imports them.
"""

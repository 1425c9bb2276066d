"""Attitude planner: MILQR plans from the current estimate to the target, published as `AttitudePlanMessage`."""

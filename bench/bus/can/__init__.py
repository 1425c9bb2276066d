"""The actuator bus: the magnetorquer protocol, driver, board, bus model, fault injector, transports."""

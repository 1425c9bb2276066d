"""A stand-in for a gtsam smoother that fails the way an indeterminate system does."""


class FailingSmoother:
    def __init__(self, real):
        self.real = real

    def update(self, *args):
        raise RuntimeError("Indeterminant linear system detected (injected)")

    def __getattr__(self, name):
        return getattr(self.real, name)

"""Seed 003 studies on the discrete model: closed-loop simulation, LQR tuning, controller comparison
and the mission metrics they are judged by. Not part of a bench run: `bench tune-lqr` and
`bench compare-controllers` start them."""

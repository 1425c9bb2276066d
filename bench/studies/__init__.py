"""Studies that run many scenarios and compare. Seed 003 studies on the discrete model: closed-loop
simulation, LQR tuning, controller comparison and the mission metrics they are judged by (`bench
tune-lqr`, `bench compare-controllers`). Seed 001 Monte Carlo campaigns (`bench campaign`)."""

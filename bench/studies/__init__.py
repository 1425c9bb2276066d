"""Studies that run many scenarios and compare: seed 003 studies, seed 001 campaigns."""

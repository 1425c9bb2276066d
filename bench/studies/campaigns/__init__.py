"""Built-in campaign specs (`bench campaign NAME`)."""

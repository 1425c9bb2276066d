"""What every bench process and the launcher share: the node context, starting a node as a process,
and deadline-miss accounting."""

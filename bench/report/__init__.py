"""Run reports: latency from header stamps, deadlines, plots, HTML/Markdown, run comparison."""

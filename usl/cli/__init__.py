"""Console entry points (usl-train, usl-eval, usl-predict, usl-records) and their shared argparse style: torch loads
only after the arguments are parsed, so every ``--help`` is quick. Library code never imports this package."""

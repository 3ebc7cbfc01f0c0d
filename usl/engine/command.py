"""The console command that runs the trainer: its messages start with this name (here, so the engine never
imports its command line)."""

COMMAND = "usl-train"

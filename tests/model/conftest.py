import sys
from pathlib import Path

# Lets the model tests import their shared helpers (detection_oracles.py, detection_scenes.py) by module name.
sys.path.insert(0, str(Path(__file__).parent))

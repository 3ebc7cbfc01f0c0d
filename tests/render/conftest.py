import sys
from pathlib import Path

# Lets the render tests import their shared pyrender oracle (render_oracle.py) by module name.
sys.path.insert(0, str(Path(__file__).parent))

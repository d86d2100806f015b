import sys

from robustbench3d.cli import main

sys.exit(main())

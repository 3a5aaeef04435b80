import sys

from maniskill_irb120.cli import main

sys.exit(main())

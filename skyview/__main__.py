import sys

from skyview.cli import main

sys.exit(main())

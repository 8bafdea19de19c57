import sys

from meshprep.cli import main

sys.exit(main())

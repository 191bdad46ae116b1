import sys

from minority.cli import main

sys.exit(main())

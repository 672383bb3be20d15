import sys

from modi.cli import main

sys.exit(main())

import sys

from surfelwarp.cli import main

sys.exit(main())

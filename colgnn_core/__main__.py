import sys

from colgnn_core.cli import main

sys.exit(main())

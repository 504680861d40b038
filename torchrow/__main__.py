import sys

from torchrow.apps.cli import main

sys.exit(main())

import sys

from zoffload.cli.main import main

sys.exit(main())

import sys

from teleop.cli.entry import main

sys.exit(main())

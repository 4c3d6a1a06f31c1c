import sys

from jaxmotion._cli.main import main

sys.exit(main())

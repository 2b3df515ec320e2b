from jaxrt.tools.cli import main

raise SystemExit(main())

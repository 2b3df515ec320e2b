from jaxrt.cli import main

raise SystemExit(main())

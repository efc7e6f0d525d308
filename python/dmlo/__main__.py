from dmlo.cli import main

raise SystemExit(main())

from chipstack.pipeline.cli import main

raise SystemExit(main())

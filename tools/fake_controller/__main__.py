from repetrel_host.testing.fake_controller import main

raise SystemExit(main())

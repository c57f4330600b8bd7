from repetrel_host.fakes.fake_controller import main

raise SystemExit(main())

"""The print server's printers: each one's service, its long-lived session and the loop
that feeds it its queue (:mod:`.service`); its settings (:mod:`.config`), the job it
streams now (:mod:`.running`), what it checks before a job starts (:mod:`.checks`), what
its jobs' host codes do (:mod:`.host_actions`), and its heaters as the page shows them
(:mod:`.heaters`)."""

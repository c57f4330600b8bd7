"""A farm: many print servers (nodes) sharing one job queue in PostgreSQL
(``hyrel-server --farm postgresql://USER@HOST/DB``)."""

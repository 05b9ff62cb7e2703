"""``python -m workers``: a Celery worker for the settings in the environment."""

from workers.worker import main

main()

"""Webhooks: registrations, the outbox delivery job (signed POSTs retried with backoff for a day,
each attempt logged), the guard on where they may go, and `robot.silent`."""

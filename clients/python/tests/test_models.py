"""Unit tests of the client's models that need no farm."""

import unittest

from tessera_client import models


def _status(**kw):
    d = {
        "id": 7, "name": None, "state": "running", "scene": "builtin:cornell-box",
        "settings": {"scene": "builtin:cornell-box"}, "width": 64, "height": 64,
        "frames_total": 1, "frames_done": 0, "tiles_total": 4, "passes_planned": 64,
        "passes_done": 8, "spp_so_far": 32.0, "error_estimate": 0.08,
        "target_error": 0.05, "elapsed_seconds": 4.0, "eta_seconds": 60.0,
        "created_unix_ms": 1, "priority": 0, "faults": 0,
    }
    d.update(kw)
    return models.JobStatus.from_json(d)


class EtaText(unittest.TestCase):
    """The progress line gives the ETA as ``tessera status`` does."""

    def test_a_point_eta_alone(self):
        self.assertTrue(_status().progress_line().endswith("eta 60 s"))

    def test_the_interval_of_a_job_that_stops_at_its_target(self):
        s = _status(eta_low_seconds=50.0, eta_high_seconds=75.0, eta_tail_class="light")
        self.assertTrue(s.progress_line().endswith("eta 60 s [50, 75 s]"), s.progress_line())

    def test_not_predictable_says_so_with_its_bounds(self):
        s = _status(eta_seconds=None, eta_low_seconds=12.0, eta_high_seconds=500.0,
                    eta_tail_class="unpredictable", eta_note="the error grew")
        self.assertEqual(s.eta_text(), "not predictable (at least 12 s, at most 500 s)")
        self.assertEqual(s.eta_note, "the error grew")

    def test_no_eta(self):
        self.assertEqual(_status(eta_seconds=None).eta_text(), "-")


if __name__ == "__main__":
    unittest.main()

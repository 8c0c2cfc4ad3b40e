"""What runs in worker processes: a solve or a calibration job, a batch's project read under limits,
and the warm-up that compiles the solver before the workers fork."""

"""Files in and out: atomic writes and hashing (:mod:`.atomic`), staged output folders
(:mod:`.outputs`), CSV tables (:mod:`.csvio`) and images (:mod:`.images`)."""

"""From photos to a posed capture: structure from motion, camera vetting, GPS, georeference, scene bounds."""

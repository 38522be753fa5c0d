"""AutoPlace radar place recognition (Cai, Wang, Lu, ICRA 2022), re-implemented.

Data side: :mod:`.prepare` (key frames, DPR, BEV images, split), :mod:`.dataset`
(:class:`~radarslam.place_recognition.dataset.PreparedData`), :mod:`.retrieval`, :mod:`.rcshr`,
:mod:`.metrics`, :mod:`.evaluate`, :mod:`.baselines`. Networks and training: :mod:`.models`,
:mod:`.train`, :mod:`.checkpoint`. The standalone loop detector is
:class:`radarslam.place_recognition.recognizer.PlaceRecognizer`.

Importing this package is light (no torch); the submodules that need torch import it themselves.
"""

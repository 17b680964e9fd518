"""The calibrated robot written out: ``calibrated.urdf`` (``urdf``), the calibrated DH table
(``dh_table``), the problem files of the calibrated robot (``calibrated_toml``) and what
``identify`` says and writes (``report``; of an artefact's recordings ``artefact_report``)."""

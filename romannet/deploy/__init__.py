"""Running the fleet across machines: the site CA and certificates, the Zenoh configs of every role, the
router, and the `romannet router` / `romannet deploy` command line. The CLI side only: actor/, learner/ and
replay/ never import it (they read the configs it writes)."""

"""Everything that imports Mitsuba 3. Modules import Mitsuba lazily so that `matcap --help` stays fast."""

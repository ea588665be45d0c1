"""Whole objects: a cloud split into regions one surface each fits, the faces fitted,
extended, cut where they meet and sewn into one shell (a solid where it closes)."""

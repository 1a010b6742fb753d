def meter(): pass
class MeterReport: pass

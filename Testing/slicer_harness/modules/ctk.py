"""``ctk`` for the test harness: stand-ins for the CTK widgets that Slicer's Python and the module touch.

Each stand-in has the properties, signals and slots of the real CTK widget (CTK ``Libs/Widgets/*.h``) that
a caller can reach; behaviour beyond the header (painting, animation) is Qt's default. Classes that
Slicer's parameterNodeWrapper only names in ``type(widget) in (...)`` checks are declared, and refuse to
be instantiated (the module does not use them), so that a test cannot silently rely on them.
"""
import qt
from PySide6.QtCore import Property, Signal, Slot


class ctkCollapsibleButton(qt.QAbstractButton):
    """ctkCollapsibleButton: a checkable header button that shows/hides its children (ctkCollapsibleButton.h)."""

    contentsCollapsed = Signal(bool)

    def __init__(self, *args):
        text = args[0] if args and isinstance(args[0], str) else ""
        parent = args[-1] if args and not isinstance(args[-1], str) else None
        super().__init__(parent)
        self.setText(text)
        self.setCheckable(True)
        self.setChecked(True)
        self._collapsedHeight = 14
        self._frameShape = qt.QFrame.NoFrame
        self._frameShadow = qt.QFrame.Plain
        self._lineWidth = 1
        self._midLineWidth = 0
        self._textAlignment = qt.Qt.AlignLeft | qt.Qt.AlignVCenter
        self._indicatorAlignment = qt.Qt.AlignLeft | qt.Qt.AlignVCenter
        self.toggled.connect(self.onToggled)

    def _getCollapsed(self):
        return not self.isChecked()

    @Slot(bool)
    def setCollapsed(self, collapsed):
        """Collapse (True) or expand (False) the contents."""
        self.setChecked(not collapsed)

    collapsed = Property(bool, _getCollapsed, setCollapsed, notify=contentsCollapsed)
    collapsedHeight = Property(int, lambda s: s._collapsedHeight, lambda s, v: setattr(s, "_collapsedHeight", v))
    contentsLineWidth = Property(int, lambda s: s._lineWidth, lambda s, v: setattr(s, "_lineWidth", v))
    contentsMidLineWidth = Property(int, lambda s: s._midLineWidth, lambda s, v: setattr(s, "_midLineWidth", v))

    contentsFrameShape = Property(object, lambda s: s._frameShape, lambda s, v: s.setContentsFrameShape(v))
    contentsFrameShadow = Property(object, lambda s: s._frameShadow, lambda s, v: s.setContentsFrameShadow(v))
    buttonTextAlignment = Property(object, lambda s: s._textAlignment, lambda s, v: s.setButtonTextAlignment(v))
    indicatorAlignment = Property(object, lambda s: s._indicatorAlignment, lambda s, v: s.setIndicatorAlignment(v))

    def setCollapsedHeight(self, h):
        self._collapsedHeight = h

    def setContentsLineWidth(self, w):
        self._lineWidth = w

    def setContentsMidLineWidth(self, w):
        self._midLineWidth = w

    def setContentsFrameShape(self, shape):
        self._frameShape = shape

    def setContentsFrameShadow(self, shadow):
        self._frameShadow = shadow

    def setButtonTextAlignment(self, a):
        self._textAlignment = a

    def setIndicatorAlignment(self, a):
        self._indicatorAlignment = a

    @Slot(bool)
    def collapse(self, c):
        """Show or hide the child widgets (protected slot in CTK)."""
        for child in self.children():
            if isinstance(child, qt.QWidget):
                child.setVisible(not c)
        self.updateGeometry()

    @Slot(bool)
    def onToggled(self, checked=False):
        self.collapse(not checked)
        self.contentsCollapsed.emit(not checked)

    def childEvent(self, event):
        super().childEvent(event)
        if event.type() == qt.QEvent.ChildPolished and self.collapsed:
            child = event.child()
            if isinstance(child, qt.QWidget):
                child.setVisible(False)

    def _headerHeight(self):
        return self.fontMetrics().height() + 10

    def sizeHint(self):
        lay = self.layout()
        h = self._headerHeight()
        w = self.fontMetrics().horizontalAdvance(self.text) + 40
        if lay is not None and not self.collapsed:
            s = lay.sizeHint()
            h += s.height() + 4
            w = max(w, s.width())
        return qt.QSize(w, h)

    def minimumSizeHint(self):
        return self.sizeHint()

    def hitButton(self, pos):
        return pos.y() < self._headerHeight()

    def resizeEvent(self, event):
        lay = self.layout()
        if lay is not None:
            lay.setContentsMargins(6, self._headerHeight() + 2, 6, 4)
        super().resizeEvent(event)

    def paintEvent(self, event):
        p = qt.QPainter(self)
        opt = qt.QStyleOptionButton()
        opt.initFrom(self)
        opt.rect = qt.QRect(0, 0, self.width, self._headerHeight())
        opt.text = ""
        self.style().drawControl(qt.QStyle.CE_PushButton, opt, p, self)
        arrow = qt.QStyle.PE_IndicatorArrowRight if self.collapsed else qt.QStyle.PE_IndicatorArrowDown
        ao = qt.QStyleOption()
        ao.initFrom(self)
        ao.rect = qt.QRect(4, 2, self._headerHeight() - 4, self._headerHeight() - 4)
        self.style().drawPrimitive(arrow, ao, p, self)
        p.drawText(qt.QRect(self._headerHeight() + 2, 0, self.width, self._headerHeight()),
                   int(qt.Qt.AlignLeft | qt.Qt.AlignVCenter), self.text)
        if not self.collapsed:
            p.setPen(self.palette.mid().color())
            p.drawRect(0, self._headerHeight(), self.width - 1, self.height - self._headerHeight() - 1)
        p.end()


class _NotStoodIn(qt.QWidget):
    """A CTK class named by Slicer's parameterNodeWrapper type checks that this module does not use."""

    def __init__(self, *args, **kwargs):
        raise NotImplementedError(f"{type(self).__name__} is not stood in by the harness")


for _name in ("ctkCheckBox", "ctkCheckablePushButton", "ctkComboBox", "ctkSliderWidget", "ctkDoubleSlider",
              "ctkDoubleSpinBox", "ctkRangeWidget", "ctkDoubleRangeSlider", "ctkPathLineEdit", "ctkDirectoryButton",
              "ctkColorPickerButton", "ctkMessageBox"):
    globals()[_name] = type(_name, (_NotStoodIn,), {})

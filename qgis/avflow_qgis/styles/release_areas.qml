<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="Symbology">
  <renderer-v2 type="singleSymbol" symbollevels="0" enableorderby="0" forceraster="0">
    <symbols>
      <symbol name="0" type="fill" alpha="1" clip_to_extent="1" force_rhr="0">
        <layer class="SimpleFill" enabled="1" locked="0" pass="0"><Option type="Map">
          <Option name="color" value="0,0,0,0" type="QString"/><Option name="outline_color" value="123,50,148,255" type="QString"/>
          <Option name="outline_style" value="solid" type="QString"/><Option name="outline_width" value="0.4" type="QString"/>
          <Option name="outline_width_unit" value="MM" type="QString"/><Option name="style" value="no" type="QString"/></Option></layer>
      </symbol>
    </symbols>
  </renderer-v2>
</qgis>
